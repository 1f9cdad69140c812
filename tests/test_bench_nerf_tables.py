"""bench_nerf.py's loss-ablation table and ``loc_rate_nerf`` on synthetic records: known
figures in the right rows and columns, and clear errors for missing runs and wrong results."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

from diffloc.config import nerf_settings
from diffloc.maps.nerf.data import SubmapDataConfig
from diffloc.maps.nerf.module import NerfTrainConfig
from diffloc.maps.nerf.submaps import SubmapConfig

ROOT = Path(__file__).resolve().parents[1]


def load_script():
    spec = importlib.util.spec_from_file_location("bench_nerf", ROOT / "experiments/bench_nerf.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run(psnr: float, depth_m: float, normal_deg: float, steps: int, t25: float | None) -> dict:
    return {
        "psnr_heldout_db": psnr,
        "depth_median_abs_err_m": depth_m,
        "normal_median_err_deg": normal_deg,
        "steps": steps,
        "train_s": 180.2,
        "train_cpu_s": 301.7,
        "time_to_25db_s": t25,
        "cpu_to_25db_s": None if t25 is None else t25 + 100,
    }


def record(variants=("full", "rgb_only", "rgb_depth")) -> dict:
    runs = {
        "full": run(26.5, 0.0194, 9.37, 500, 120.0),
        "rgb_only": run(24.0, 0.4, 60.0, 800, None),
        "rgb_depth": run(26.0, 0.021, 20.4, 600, 150.0),
        "uncontracted": run(22.0, 0.35, 30.0, 450, None),
    }
    out = {
        "data": "data/indoor_seed0",
        "submap": 0,
        "train_frames": 64,
        "threads": 2,
        "budget_s": 180.0,
        "ablation_budget_s": 180.0,
        "load_avg_start": 2.04,
        "load_avg_end": 2.51,
        "clock": "wall",
    }
    for variant in variants:
        suffix = "" if variant == "full" else f"_{variant}"
        out |= {f"{k}{suffix}": v for k, v in runs[variant].items()}
    return out


def table_rows(text: str) -> dict[str, list[str]]:
    rows = [line.strip("|").split("|") for line in text.splitlines() if line.startswith("| ")]
    return {cells[0].strip(): [c.strip() for c in cells[1:]] for cells in rows}


def test_ablation_table_puts_each_run_in_its_row():
    bench = load_script()
    text = bench.ablation_markdown(record())
    rows = table_rows(text)
    assert rows["photometric only"] == [
        "24.00",
        "40.0",
        "60.0",
        "800",
        "180",
        "302",
        "not reached",
        "not reached",
    ]
    assert rows["photometric + depth (Eq. 6)"] == [
        "26.00",
        "2.1",
        "20.4",
        "600",
        "180",
        "302",
        "150",
        "250",
    ]
    full = rows["photometric + depth + normals (Eq. 6, 7)"]
    assert full == ["26.50", "1.9", "9.4", "500", "180", "302", "120", "220"]
    assert "2 thread(s) per process" in text and "180 s wall-clock budget" in text
    assert "load 2.0 at the start, 2.5 at the end" in text
    assert not any("another moment" in name for name in rows)


def test_ablation_table_marks_the_reference_row():
    bench = load_script()
    reference = record(("full",)) | {"psnr_heldout_db": 26.68, "load_avg_start": 0.7}
    rows = table_rows(bench.ablation_markdown(record(), reference))
    label = (
        "photometric + depth + normals (Eq. 6, 7), measured at another moment (2 thread(s), "
        "180 s wall-clock budget, load 0.7 at the start)"
    )
    assert rows[label][0] == "26.68"
    assert list(rows)[-1] == label and len(rows) == 5  # header, 3 runs, reference


def test_ablation_table_takes_the_full_run_from_the_reference():
    bench = load_script()
    reference = record(("full",)) | {"clock": "cpu", "threads": 1, "load_avg_start": 19.6}
    del reference["budget_s"], reference["ablation_budget_s"]
    rows = table_rows(bench.ablation_markdown(record(("rgb_only", "rgb_depth")), reference))
    assert "photometric + depth + normals (Eq. 6, 7)" not in rows
    label = (
        "photometric + depth + normals (Eq. 6, 7), measured at another moment (1 thread(s), "
        "302 s cpu-clock budget, load 19.6 at the start)"
    )
    assert rows[label][:3] == ["26.50", "1.9", "9.4"]


def test_ablation_table_names_the_missing_runs():
    bench = load_script()
    with pytest.raises(ValueError, match=r"\['rgb_depth'\].*--variants full,rgb_only,rgb_depth"):
        bench.ablation_markdown(record(("full", "rgb_only")))
    with pytest.raises(ValueError, match=r"\['full'\].*--ablation-reference"):
        bench.ablation_markdown(record(("rgb_only", "rgb_depth")))


def test_contraction_table_puts_each_field_in_its_row_after_the_command():
    bench = load_script()
    command = "python3 experiments/bench_nerf.py --scene outdoor --variants full,uncontracted"
    text = bench.contraction_markdown(record(("full", "uncontracted")) | {"command": command})
    assert text.startswith(f"Made by: `{command}`")
    rows = table_rows(text)
    assert rows["no contraction, the same box"][:4] == ["22.00", "35.0", "30.0", "450"]
    assert rows["mip-NeRF 360 contraction"][:4] == ["26.50", "1.9", "9.4", "500"]
    assert list(rows)[1:] == ["no contraction, the same box", "mip-NeRF 360 contraction"]
    merged = record(("full", "uncontracted")) | {
        "command": "python3 experiments/bench_nerf.py --merge a.jsonl b.jsonl",
        "parts": [
            {"command": "python3 a", "load_avg_start": 3.5},
            {"command": "python3 b", "load_avg_start": 3.9},
        ],
    }
    lines = bench.contraction_markdown(merged).splitlines()
    assert lines[1] == "merging the last records of `python3 a`, `python3 b`"
    assert "2 processes merged by --merge (loads at their starts: 3.5, 3.9)" in lines[3]
    with pytest.raises(ValueError, match=r"has \['full'\].*--variants full,uncontracted"):
        bench.contraction_markdown(record(("full",)))
    with pytest.raises(ValueError, match=r"has \['uncontracted'\]"):
        bench.contraction_markdown(record(("uncontracted",)))


def test_the_outdoor_variant_switches_only_the_contraction_off():
    bench = load_script()
    outdoor = nerf_settings("outdoor")
    assert outdoor.train.field.contracted and outdoor.data.lidar_max_range_m == 80.0
    plain = bench.variant_config(outdoor.train, "hashgrid", "uncontracted")
    assert not plain.field.contracted and plain.field.encoding == "hashgrid"
    assert plain.loss == outdoor.train.loss and plain.sampler == outdoor.train.sampler


def test_the_indoor_settings_are_the_defaults_the_benchmark_used_before():
    indoor = nerf_settings("indoor")
    assert indoor.train == NerfTrainConfig() and not indoor.train.field.contracted
    assert indoor.data == SubmapDataConfig()
    assert indoor.submaps == SubmapConfig(num_submaps=4)


def results(tmp_path: Path, map_name: str, loose_m: float, sequences: dict) -> Path:
    path = tmp_path / "results.json"
    label = f"{loose_m:g}m_30deg"
    entries = {
        name: {"rates": {"0.25m_2deg": 0.0, "0.5m_5deg": rate / 2, label: rate}}
        for name, rate in sequences.items()
    }
    path.write_text(json.dumps({"map": map_name, "loose_m": loose_m, "sequences": entries}))
    return path


def test_loc_rate_reads_the_loose_rate_of_both_sequences(tmp_path):
    bench = load_script()
    out = {}
    path = results(tmp_path, "nerf", 1.0, {"query_same": 0.75, "query_reverse": 0.5})
    bench.add_loc_rate(out, path)
    assert out == {
        "loc_rate_nerf": 0.75,
        "loc_rate_nerf_query_reverse": 0.5,
        "loc_results": str(path),
    }


def test_loc_rate_uses_the_runs_loose_bound(tmp_path):
    bench = load_script()
    out = {}
    bench.add_loc_rate(out, results(tmp_path, "nerf", 2.0, {"query_same": 0.25}))
    assert out["loc_rate_nerf"] == 0.25 and "loc_rate_nerf_query_reverse" not in out


def test_loc_rate_refuses_another_map(tmp_path):
    bench = load_script()
    path = results(tmp_path, "cloud", 1.0, {"query_same": 0.5})
    with pytest.raises(ValueError, match=r"results.json is a map=cloud run.*map=nerf"):
        bench.add_loc_rate({}, path)


def test_loc_rate_needs_query_same(tmp_path):
    bench = load_script()
    path = results(tmp_path, "nerf", 1.0, {"query_reverse": 0.5})
    with pytest.raises(ValueError, match=r"no query_same sequence.*task.sequences"):
        bench.add_loc_rate({}, path)

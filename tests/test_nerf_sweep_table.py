"""experiments/nerf_sweep_table.py on synthetic bench_nerf records: differences to the run
without overrides of the same dataset and to the default of the same training seed, PSNR at
the CPU marks, and a clear error for a record without the full variant."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def load_script():
    path = ROOT / "experiments/nerf_sweep_table.py"
    spec = importlib.util.spec_from_file_location("nerf_sweep_table", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def record(data: str, psnr: float, overrides: list[str] | None) -> dict:
    out = {
        "command": "python3 experiments/bench_nerf.py",
        "data": data,
        "psnr_heldout_db": psnr,
        "psnr_heldout_surface_db": psnr - 1.0,
        "psnr_heldout_sky_db": psnr + 2.0,
        "depth_median_abs_err_m": 0.067,
        "normal_median_err_deg": 1.45,
        "steps": 900,
        "cpu_ms_per_step": 198.5,
        "train_cpu_s": 180.1,
        "curve": [[45.0, 30.2, 176, 21.0], [105.0, 60.2, 346, 22.0], [310.0, 120.0, 620, 22.5]],
        "load_avg_start": 3.5,
        "load_avg_end": 4.0,
    }
    if overrides is not None:  # records written before the key existed have none
        out["overrides"] = overrides
    return out


def test_rows_name_the_file_each_run_wrote_and_its_render_time() -> None:
    script = load_script()
    command = "python3 experiments/bench_nerf.py --out experiments/results/speed_seed0.jsonl"
    rows = script.sweep_rows(
        [record("data/outdoor_seed0", 22.5, []) | {"command": command, "render_320x240_cpu_s": 1.9}]
    )
    assert rows[0]["run"] == "speed_seed0" and rows[0]["render_cpu_s"] == 1.9
    assert "| speed_seed0 | outdoor_seed0 | 22.50 |" in script.sweep_markdown(rows, "cmd")
    assert "| 1.90 | 3.5 / 4.0 |" in script.sweep_markdown(rows, "cmd")


def test_rows_compare_with_the_default_of_the_same_dataset() -> None:
    script = load_script()
    rows = script.sweep_rows(
        [
            record("data/outdoor_seed0", 22.5, None),
            record("data/outdoor_seed0", 23.0, ["nerf.train.ray_batch=2048"]),
            record("data/outdoor_seed1", 22.0, []),
            record("data/outdoor_seed1", 21.5, ["nerf.train.ray_batch=2048"])
            | {"sky_opacity_mean": 0.9981},
            record("data/other", 20.0, ["nerf.train.ray_batch=2048"]),
            record("data/outdoor_seed0", 21.0, []) | {"encodings": "hashgrid"},
        ]
    )
    assert rows[5]["setting"] == "--encodings hashgrid"
    assert [r["run"] for r in rows[:2]] == ["-", "-"] and rows[0]["render_cpu_s"] is None
    assert rows[5]["delta_db"] == pytest.approx(-1.5)
    assert [r["setting"] for r in rows[:2]] == ["default", "nerf.train.ray_batch=2048"]
    assert rows[0]["delta_db"] == 0.0 and rows[2]["delta_db"] == 0.0
    assert rows[1]["delta_db"] == pytest.approx(0.5)
    assert rows[3]["delta_db"] == pytest.approx(-0.5)
    assert rows[4]["delta_db"] is None
    assert rows[0]["psnr_at_60s_db"] == 22.0 and rows[0]["psnr_at_120s_db"] == 22.5
    assert rows[0]["depth_cm"] == pytest.approx(6.7)
    text = script.sweep_markdown(rows, "python3 x.py")
    assert text.startswith("Made by: `python3 x.py`")
    row = (
        "| `nerf.train.ray_batch=2048` | - | outdoor_seed1 | 21.50 | -0.50 | -0.50 | "
        "20.50 / 23.50 |"
    )
    assert row + " 0.998 | 6.7 |" in text
    assert "| 20.00 / 23.00 | - | 6.7 |" in text  # no sky opacity in the record


def test_rows_compare_with_the_default_of_the_same_training_seed() -> None:
    script = load_script()
    rows = script.sweep_rows(
        [
            record("data/outdoor_seed0", 22.5, []),
            record("data/outdoor_seed0", 23.0, ["nerf.train.seed=1"]),
            record("data/outdoor_seed0", 23.4, ["nerf.train.seed=1", "nerf.train.ray_batch=8"]),
            record("data/outdoor_seed0", 22.9, ["nerf.train.ray_batch=8", "nerf.train.seed=0"]),
            record("data/outdoor_seed0", 21.0, ["nerf.train.seed=2", "nerf.train.ray_batch=8"]),
        ]
    )
    assert rows[1]["delta_db"] == pytest.approx(0.5) and rows[1]["delta_same_seed_db"] == 0.0
    assert rows[2]["delta_db"] == pytest.approx(0.9)
    assert rows[2]["delta_same_seed_db"] == pytest.approx(0.4)
    assert rows[3]["delta_same_seed_db"] == pytest.approx(0.4)
    assert rows[4]["delta_same_seed_db"] is None


def test_a_mark_after_the_run_is_empty() -> None:
    script = load_script()
    curve = [[45.0, 30.2, 176, 21.0]]
    assert script._at_mark(curve, 30.0) == 21.0
    assert script._at_mark(curve, 60.0) is None


def test_a_record_without_the_full_variant_is_refused() -> None:
    script = load_script()
    bad = record("data/outdoor_seed0", 22.5, None)
    del bad["psnr_heldout_db"]
    with pytest.raises(ValueError, match="no full-variant run"):
        script.sweep_rows([bad])

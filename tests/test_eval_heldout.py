"""Held-out seed reports on synthetic run folders: loading sweeps, seed statistics with known
numbers, the Markdown/JSON report, and clear errors for empty, half-finished or old runs."""

from __future__ import annotations

import importlib.util
import json
import math
import shutil
from pathlib import Path

import pytest

from diffloc.eval.heldout import FIGURES, heldout_markdown, heldout_rows, seed_statistics
from diffloc.eval.sweeps import check_held_out, group_variants, load_job, load_jobs
from tests.fake_runs import sequence_entry, write_job, write_multirun

ROOT = Path(__file__).resolve().parents[1]

# Seeds 1-3 of one variant: recall@0.3 0.9 / 0.7 / 0.8, mATE 2 / 5 / 3 cm, 10 / 30 / 20 ms,
# precision undefined on seed 3 (nothing accepted).
SEEDS = {
    1: sequence_entry((0.5, 0.9, 1.0), 0.95, 0.02, 10.0, 40, 0.6, 6.0),
    2: sequence_entry((0.3, 0.7, 0.8), 0.80, 0.05, 30.0, 40, 0.4, 4.0),
    3: sequence_entry((0.4, 0.8, 0.9), None, 0.03, 20.0, 40, 0.5, 5.0),
}


def load_script():
    spec = importlib.util.spec_from_file_location("heldout_script", ROOT / "experiments/heldout.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main_sweep(root: Path, seeds=(1, 2, 3)) -> Path:
    """``diffloc -m task=main scene.seed=1,2,3``: one job per seed, sequence ``query_same``."""
    sweep = root / "heldout_main"
    write_multirun(sweep, ["task=main", "scene.seed=" + ",".join(map(str, seeds))])
    for i, seed in enumerate(seeds):
        write_job(sweep / str(i), ["task=main", f"scene.seed={seed}"], {"query_same": SEEDS[seed]})
    return sweep


def row(rows, figure, variant=None):
    (match,) = [
        r for r in rows if r["figure"] == figure and (variant is None or r["variant"] == variant)
    ]
    return match


def cells(text: str, figure: str) -> list[str]:
    """The cells after variant, sequence and figure of the Markdown row of ``figure``."""
    line = next(x for x in text.splitlines() if figure in x)
    return [c.strip() for c in line.strip("|").split("|")][3:]


def test_seed_statistics_known_numbers() -> None:
    s = seed_statistics({1: 0.9, 2: 0.7, 3: 0.8}, "min")
    assert s.mean == pytest.approx(0.8) and s.std == pytest.approx(0.1)
    assert (s.worst_seed, s.worst, s.n) == (2, 0.7, 3)
    s = seed_statistics({4: 2.0, 5: 6.0, 6: 6.0}, "max")
    assert (s.worst_seed, s.worst) == (5, 6.0)  # ties: the smallest seed
    assert s.std == pytest.approx(math.sqrt(((8 / 3) ** 2 + 2 * (4 / 3) ** 2) / 2))
    single = seed_statistics({7: 0.5, 8: None}, "min")
    assert (single.n, single.mean, single.std, single.worst_seed) == (1, 0.5, None, 7)
    assert seed_statistics({1: None}, "max").mean is None
    with pytest.raises(ValueError, match="at least one seed"):
        seed_statistics({}, "min")
    with pytest.raises(ValueError, match="worst"):
        seed_statistics({1: 1.0}, "lowest")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="non-finite"):
        seed_statistics({1: math.nan}, "min")


def test_rows_of_a_main_sweep(tmp_path: Path) -> None:
    jobs = load_jobs([main_sweep(tmp_path)])
    assert [j.seed for j in jobs] == [1, 2, 3] and {j.variant for j in jobs} == {""}
    rows = heldout_rows(group_variants(jobs))
    assert len(rows) == len(FIGURES)
    recall = row(rows, "recall@0.3m [%]")
    assert recall["values"] == {"1": 0.9, "2": 0.7, "3": 0.8}
    assert recall["mean"] == pytest.approx(0.8) and recall["std"] == pytest.approx(0.1)
    assert (recall["worst_seed"], recall["worst"]) == (2, 0.7)
    assert recall["queries"] == {"1": 40, "2": 40, "3": 40}
    assert row(rows, "recall@0.1m [%]")["worst_seed"] == 2
    mate = row(rows, "mATE [cm]")
    assert mate["mean"] == pytest.approx(0.1 / 3) and (mate["worst_seed"], mate["worst"]) == (
        2,
        0.05,
    )
    assert row(rows, "median reloc [ms]")["worst_seed"] == 2
    precision = row(rows, "precision@0.3m [%]")
    assert precision["n"] == 2 and precision["mean"] == pytest.approx(0.875)
    assert precision["worst_seed"] == 2
    distance = row(rows, "nearest DB pose, median [m]")
    assert distance["mean"] == pytest.approx(0.5) and distance["worst_seed"] == 2
    text = heldout_markdown(rows)
    assert cells(text, "recall@0.3m") == ["90.0", "70.0", "80.0", "80.0", "10.0", "70.0 (seed 2)"]
    assert cells(text, "precision") == ["95.0", "80.0", "-", "87.5", "10.6", "80.0 (seed 2)"]
    assert cells(text, "mATE") == ["2.0", "5.0", "3.0", "3.3", "1.5", "5.0 (seed 2)"]


def test_table3_style_sweep_groups_variants_over_seeds(tmp_path: Path) -> None:
    """``task.optimize=true,false`` x ``scene.seed=1,2``: statistics per variant; Hydra's
    ``True``/``true`` spellings are the same variant."""
    sweep = tmp_path / "noise"
    write_multirun(sweep, ["task=main", "scene.seed=1,2", "task.optimize=true,false"])
    recalls = {(1, True): 0.9, (1, False): 0.5, (2, True): 0.7, (2, False): 0.3}
    for i, ((seed, optimize), recall) in enumerate(recalls.items()):
        spelled = str(optimize) if seed == 1 else str(optimize).lower()
        write_job(
            sweep / str(i),
            ["task=main", f"scene.seed={seed}", "db.noise_sigma=0.2", f"task.optimize={spelled}"],
            {"query_same": sequence_entry((0.1, recall, 1.0))},
        )
    groups = group_variants(load_jobs([sweep]))
    assert [g.seeds for g in groups] == [(1, 2), (1, 2)]
    rows = heldout_rows(groups, [f for f in FIGURES if f.name.startswith("recall@0.3")])
    by_variant = {r["variant"]: r for r in rows}
    optimised = by_variant["db.noise_sigma=0.2 task.optimize=True"]
    raw = by_variant["db.noise_sigma=0.2 task.optimize=False"]
    assert optimised["mean"] == pytest.approx(0.8) and raw["mean"] == pytest.approx(0.4)
    assert optimised["std"] == pytest.approx(math.sqrt(0.02)) and raw["worst_seed"] == 2


def test_several_folders_and_seed_from_config(tmp_path: Path) -> None:
    """Single job folders (``diffloc task=main``) combine; the seed may come from config.yaml."""
    one = write_job(tmp_path / "a", [], {"query_same": SEEDS[1]}, config_seed=1)
    two = write_job(tmp_path / "b", ["scene.seed=2"], {"query_same": SEEDS[2]}, config_seed=0)
    jobs = load_jobs([one, two])
    assert [j.seed for j in jobs] == [1, 2]
    assert row(heldout_rows(group_variants(jobs)), "recall@0.3m [%]")["mean"] == pytest.approx(0.8)


def test_cli_writes_md_and_json_headed_by_the_command(tmp_path: Path) -> None:
    sweep = main_sweep(tmp_path)
    command = f"diffloc -m task=main scene.seed=1,2,3 hydra.sweep.dir={sweep}"
    out = load_script().main(
        ["stats", str(sweep), "--name", "main", "--command", command, "--note", "A note."]
        + ["--results-dir", str(tmp_path / "results")]
    )
    assert out == tmp_path / "results" / "heldout_main.md"
    text = out.read_text()
    assert text.startswith(f"Made by:\n\n```bash\n{command}\npython3 experiments/heldout.py stats")
    assert "A note." in text and "| 70.0 (seed 2) |" in text
    rows = json.loads(out.with_suffix(".json").read_text())
    assert row(rows, "recall@0.3m [%]")["worst_seed"] == 2


def test_empty_and_half_finished_sweeps_raise(tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match="neither a job folder"):
        load_jobs([empty])
    with pytest.raises(ValueError, match="no run or sweep folders"):
        load_jobs([])
    with pytest.raises(FileNotFoundError, match="not a folder"):
        load_jobs([tmp_path / "missing"])
    started = tmp_path / "started"
    write_multirun(started, ["scene.seed=1,2,3"])
    with pytest.raises(ValueError, match="0 job folders but multirun.yaml describes 3"):
        load_jobs([started])
    sweep = main_sweep(tmp_path, seeds=(1, 2, 3))
    (sweep / "2" / "results.json").unlink()  # the last job is still running
    with pytest.raises(ValueError, match="half-finished sweep, jobs 2 of 3"):
        load_jobs([sweep])
    shutil.rmtree(sweep / "2")  # its folder not even made yet
    with pytest.raises(ValueError, match="2 job folders but multirun.yaml describes 3"):
        load_jobs([sweep])


def test_old_results_without_new_keys_name_the_key(tmp_path: Path) -> None:
    entry = sequence_entry()
    del entry["recall_at"]
    job = write_job(tmp_path / "old", ["scene.seed=4"], {"query_same": entry})
    with pytest.raises(ValueError, match="no 'recall_at' in the results"):
        heldout_rows(group_variants([load_job(job)]))
    entry = sequence_entry()
    del entry["nearest_db_pose"]["angle_median_deg"]
    job = write_job(tmp_path / "old2", ["scene.seed=4"], {"query_same": entry})
    with pytest.raises(ValueError, match="no 'nearest_db_pose.angle_median_deg'"):
        heldout_rows(group_variants([load_job(job)]))


def test_inconsistent_runs_raise(tmp_path: Path) -> None:
    a = write_job(tmp_path / "a", ["scene.seed=1"], {"query_same": SEEDS[1]})
    b = write_job(tmp_path / "b", ["scene.seed=1"], {"query_same": SEEDS[2]})
    with pytest.raises(ValueError, match="two jobs of variant '' on scene seed 1"):
        group_variants(load_jobs([a, b]))
    c = write_job(tmp_path / "c", ["scene.seed=2"], {"changed": SEEDS[2]})
    with pytest.raises(ValueError, match="relocalised"):
        heldout_rows(group_variants(load_jobs([a, c])))
    zero = write_job(tmp_path / "z", [], {"query_same": SEEDS[1]}, config_seed=0)
    with pytest.raises(ValueError, match="used for tuning"):
        check_held_out(load_jobs([a, zero]))
    check_held_out(load_jobs([a, zero]), tuning_seeds=())
    no_seed = write_job(tmp_path / "n", [], {"query_same": SEEDS[1]})
    with pytest.raises(FileNotFoundError, match="cannot tell the scene seed"):
        load_job(no_seed)
    with pytest.raises(FileNotFoundError, match="did not finish"):
        load_job(tmp_path)

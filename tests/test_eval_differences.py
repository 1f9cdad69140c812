"""Paired differences between variants over held-out seeds, on synthetic sweep folders."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

from diffloc.eval.differences import Comparison, difference_markdown, difference_rows
from diffloc.eval.sweeps import load_jobs
from tests.fake_runs import query_list, sequence_entry, write_job, write_multirun

ROOT = Path(__file__).resolve().parents[1]
SEQUENCES = ("query_same", "changed")
Q = 50


def correct(points: str, retriever: str) -> list[bool]:
    """FN right on every query; F wrong on the first 30 %; naive = F with netvlad, and with
    bow naive is right where F is wrong and wrong on the last 30 % (same rate, other queries)."""
    if points == "FN":
        return [True] * Q
    if points == "naive" and retriever == "bow":
        return [i < Q - 15 for i in range(Q)]
    return [i >= 15 for i in range(Q)]


def ablation_sweep(root: Path, seeds=(1, 2), points=("naive", "F", "FN")) -> Path:
    """``diffloc -m task=relocalize scene.seed=1,2 reloc.method.points=naive,F,FN
    retriever=netvlad,bow``."""
    sweep = root / "ablation"
    write_multirun(
        sweep,
        ["task=relocalize", "scene.seed=" + ",".join(map(str, seeds))]
        + ["reloc.method.points=" + ",".join(points), "retriever=netvlad,bow"],
    )
    i = 0
    for seed in seeds:
        for p in points:
            for r in ("netvlad", "bow"):
                outcomes = correct(p, r)
                write_job(
                    sweep / str(i),
                    ["task=relocalize", f"scene.seed={seed}"]
                    + [f"reloc.method.points={p}", f"retriever={r}"],
                    {s: sequence_entry(queries=Q) for s in SEQUENCES},
                    {s: query_list(outcomes, t0=100.0 * seed) for s in SEQUENCES},
                )
                i += 1
    return sweep


COMPARISONS = [
    Comparison.parse("reloc.method.points=FN,F"),
    Comparison.parse("reloc.method.points=F,naive"),
]


def find(rows, comparison, context, sequence="all"):
    (match,) = [
        r
        for r in rows
        if r["comparison"].endswith(comparison)
        and r["context"] == context
        and r["sequence"] == sequence
    ]
    return match


def test_known_differences_and_verdicts(tmp_path: Path) -> None:
    jobs = load_jobs([ablation_sweep(tmp_path)])
    rows = difference_rows(jobs, COMPARISONS, resamples=2000)
    # 2 comparisons x 2 retrievers x (pooled + 2 sequences).
    assert len(rows) == 12
    fn_f = find(rows, "FN - F", "retriever=netvlad")
    assert fn_f["queries"] == 2 * len(SEQUENCES) * Q and fn_f["strata"] == 4
    assert fn_f["seeds"] == [1, 2] and fn_f["difference"] == pytest.approx(0.3)
    assert 0.2 < fn_f["low"] < 0.3 < fn_f["high"] < 0.4 and fn_f["ordering_holds"] == "yes"
    per_sequence = find(rows, "FN - F", "retriever=bow", "changed")
    assert per_sequence["queries"] == 2 * Q and per_sequence["strata"] == 2
    # Identical outcomes: the interval is the point 0.
    same = find(rows, "F - naive", "retriever=netvlad")
    assert (same["difference"], same["low"], same["high"]) == (0.0, 0.0, 0.0)
    assert same["ordering_holds"] == "no (interval holds 0)"
    # Same success rate on different queries: zero difference with a wide interval.
    swapped = find(rows, "F - naive", "retriever=bow")
    assert swapped["difference"] == pytest.approx(0.0) and swapped["low"] < -0.05
    assert swapped["high"] > 0.05 and swapped["ordering_holds"] == "no (interval holds 0)"
    reversed_rows = difference_rows(jobs, [Comparison.parse("reloc.method.points=F,FN")])
    assert {r["ordering_holds"] for r in reversed_rows} == {"no (reversed)"}
    # Deterministic for a fixed bootstrap seed.
    assert difference_rows(jobs, COMPARISONS, resamples=2000) == rows
    text = difference_markdown(rows)
    line = next(x for x in text.splitlines() if "FN - F" in x and "netvlad" in x and "| all" in x)
    assert "| 1,2 " in line and "|  200 |" in line and "+30.0" in line and "| yes " in line


def test_cli_writes_the_differences_report(tmp_path: Path) -> None:
    sweep = ablation_sweep(tmp_path)
    spec = importlib.util.spec_from_file_location("heldout_script", ROOT / "experiments/heldout.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    out = script.main(
        ["differences", str(sweep), "--name", "ablation", "--command", "diffloc -m x"]
        + ["--compare", "reloc.method.points=FN,F", "--resamples", "500"]
        + ["--results-dir", str(tmp_path)]
    )
    assert out == tmp_path / "heldout_ablation_differences.md"
    text = out.read_text()
    assert "--compare reloc.method.points=FN,F" in text and "95 % interval [pp]" in text
    rows = json.loads(out.with_suffix(".json").read_text())
    assert len(rows) == 6 and rows[0]["resamples"] == 500


def test_comparison_parse() -> None:
    c = Comparison.parse("task.optimize=true,false")
    assert (c.key, c.better, c.worse) == ("task.optimize", True, False)
    assert c.label == "task.optimize: True - False"
    for bad in ("task.optimize=true", "a=1,2,3", "a=1,1", "=1,2"):
        with pytest.raises(ValueError, match="comparison"):
            Comparison.parse(bad)


def test_unpairable_runs_raise(tmp_path: Path) -> None:
    jobs = load_jobs([ablation_sweep(tmp_path)])
    with pytest.raises(ValueError, match="no job sets reloc.method.points=SIFT"):
        difference_rows(jobs, [Comparison.parse("reloc.method.points=SIFT,F")])
    with pytest.raises(ValueError, match="at least one comparison"):
        difference_rows(jobs, [])
    # A context with one side only (F with bow missing).
    fewer = [
        j
        for j in jobs
        if not (j.settings["reloc.method.points"] == "F" and j.settings["retriever"] == "bow")
    ]
    with pytest.raises(ValueError, match="only one side"):
        difference_rows(fewer, COMPARISONS[:1])
    # One variant missing a seed.
    fewer = [j for j in jobs if not (j.seed == 2 and j.settings["reloc.method.points"] == "F")]
    with pytest.raises(ValueError, match="seeds"):
        difference_rows(fewer, COMPARISONS[:1])


def test_other_queries_or_old_queries_raise(tmp_path: Path) -> None:
    sweep = ablation_sweep(tmp_path, seeds=(1,), points=("F", "FN"))
    jobs = load_jobs([sweep])
    path = sweep / "0" / "changed" / "queries.json"  # F netvlad, seed 1
    queries = json.loads(path.read_text())
    path.write_text(json.dumps(queries[:-1]))
    with pytest.raises(ValueError, match="do not hold the same queries"):
        difference_rows(jobs, COMPARISONS[:1])
    for q in queries:
        del q["correct"]
    path.write_text(json.dumps(queries))
    with pytest.raises(ValueError, match="no bool 'correct'"):
        difference_rows(jobs, COMPARISONS[:1])
    (sweep / "0" / "changed" / "queries.json").unlink()
    with pytest.raises(FileNotFoundError, match="queries.json is missing"):
        difference_rows(jobs, COMPARISONS[:1])

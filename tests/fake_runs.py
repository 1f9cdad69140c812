"""Synthetic job and sweep folders laid out like ``diffloc task=main`` / ``diffloc -m`` writes them.

Only the files the held-out evaluation reads: ``results.json``, ``<sequence>/queries.json``,
``.hydra/overrides.yaml``, ``.hydra/config.yaml`` and the sweep's ``multirun.yaml``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import yaml


def sequence_entry(
    recall: tuple[float, float, float] = (0.5, 0.8, 0.9),
    precision: float | None = 0.9,
    mATE_m: float | None = 0.05,
    reloc_ms: float | None = 20.0,
    queries: int = 10,
    distance_m: float = 0.4,
    angle_deg: float = 5.0,
) -> dict:
    """A ``results["sequences"][name]`` entry with the keys the held-out report reads."""
    return {
        "recall": recall[1],
        "recall_at": {"0.1": recall[0], "0.3": recall[1], "1.0": recall[2]},
        "precision": precision,
        "mATE_m": mATE_m,
        "queries": queries,
        "median_reloc_ms": reloc_ms,
        "nearest_db_pose": {
            "distance_median_m": distance_m,
            "distance_p90_m": 2 * distance_m,
            "angle_median_deg": angle_deg,
            "angle_p90_deg": 2 * angle_deg,
        },
        "seed1_rule": {"accepted": queries, "precision": precision, "recall": recall[1]},
    }


def query_list(correct: Sequence[bool], t0: float = 0.0) -> list[dict]:
    """A ``queries.json`` list: one query per second from ``t0``."""
    return [
        {
            "timestamp": t0 + i,
            "found": True,
            "accepted": bool(c),
            "correct": bool(c),
            "inliers": 50,
            "translation_error_m": 0.05 if c else 1.0,
            "rotation_error_deg": 0.5,
            "timings_ms": {"pnp": 1.0},
        }
        for i, c in enumerate(correct)
    ]


def write_job(
    folder: Path,
    overrides: Sequence[str],
    entries: dict[str, dict],
    queries: dict[str, list[dict]] | None = None,
    config_seed: int | None = None,
) -> Path:
    """A finished job folder.

    Args:
        folder: where to write.
        overrides: the job's Hydra overrides (e.g. ``["task=main", "scene.seed=2"]``).
        entries: sequence -> results entry (:func:`sequence_entry`).
        queries: sequence -> ``queries.json`` list (:func:`query_list`); none by default.
        config_seed: ``scene.seed`` in ``.hydra/config.yaml`` (none written if None).
    """
    (folder / ".hydra").mkdir(parents=True, exist_ok=True)
    (folder / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(list(overrides)))
    if config_seed is not None:
        config = {"scene": {"name": "indoor", "seed": config_seed}, "task": {"name": "main"}}
        (folder / ".hydra" / "config.yaml").write_text(yaml.safe_dump(config))
    for name, items in (queries or {}).items():
        (folder / name).mkdir(exist_ok=True)
        (folder / name / "queries.json").write_text(json.dumps(items))
    results = {"sequences": entries, "config": {}}
    (folder / "results.json").write_text(json.dumps(results))
    return folder


def write_multirun(sweep: Path, sweep_overrides: Sequence[str]) -> None:
    """The sweep's ``multirun.yaml`` with its command-line overrides (e.g. ``scene.seed=1,2``)."""
    sweep.mkdir(parents=True, exist_ok=True)
    config = {
        "hydra": {
            "mode": "MULTIRUN",
            "sweeper": {"params": None},
            "overrides": {"hydra": [f"hydra.sweep.dir={sweep}"], "task": list(sweep_overrides)},
        }
    }
    (sweep / "multirun.yaml").write_text(yaml.safe_dump(config))

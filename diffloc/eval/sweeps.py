"""Finished relocalisation jobs of Hydra runs and multirun sweeps, for held-out evaluation.

A job folder is what ``diffloc task=main`` / ``task=relocalize`` writes: ``results.json``
(per query sequence under ``results["sequences"][name]``), ``<sequence>/queries.json`` (one
entry per query) and Hydra's ``.hydra/overrides.yaml`` and ``.hydra/config.yaml``. A sweep
folder (``diffloc -m ... hydra.sweep.dir=DIR``) holds ``multirun.yaml`` and one numbered job
folder per job.

Every job has a *scene seed* (``scene.seed=N`` in its overrides, else ``scene.seed`` of its
``.hydra/config.yaml``) and a *variant*: its overrides without ``hydra.*``, ``task=``,
``+experiment=`` and ``scene.seed``, so the same variant on several seeds groups together,
across sweep folders.

Reading is strict: an empty or half-finished sweep (fewer finished jobs than ``multirun.yaml``
describes, or job folders without ``results.json``), two jobs of one variant on the same seed,
or a results file without a key the evaluation needs all raise ``ValueError`` or
``FileNotFoundError`` naming the folder and what is missing.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import Override

__all__ = [
    "Job",
    "VariantJobs",
    "check_held_out",
    "group_variants",
    "load_job",
    "load_jobs",
    "nested_value",
]

_SEED_KEY = "scene.seed"
_NOT_VARIANT = ("task", "experiment", "progress", _SEED_KEY)
"""Override keys that do not make a variant (besides ``hydra.*``): the task, the named setup
(``+experiment=NAME``, the same for every job of its sweep), progress bars (output only) and
the scene seed."""


def _parse_overrides(lines: Sequence[str], where: Path) -> list[Override]:
    try:
        return OverridesParser.create().parse_overrides(list(lines))
    except Exception as exc:  # Hydra raises its own OverrideParseException
        raise ValueError(f"{where}: cannot parse the overrides {list(lines)}: {exc}") from exc


def _canonical(value: object) -> str:
    """A hashable text of an override value (``True`` == ``true``, ``0.20`` == ``0.2``)."""
    return json.dumps(value, sort_keys=True, default=str)


@dataclass(frozen=True)
class Job:
    """One finished job.

    Attributes:
        folder: the job folder.
        seed: the scene seed.
        overrides: the job's overrides as written, ``hydra.*`` left out.
        settings: the variant's overrides, key -> parsed value (``hydra.*``, ``task`` and
            ``scene.seed`` left out).
        results: the content of ``results.json``.
    """

    folder: Path
    seed: int
    overrides: tuple[str, ...]
    settings: Mapping[str, object] = field(compare=False)
    results: Mapping[str, object] = field(compare=False, repr=False)

    @property
    def variant(self) -> str:
        """The variant's overrides as written, space-separated (``""`` for the defaults)."""
        skip = tuple(f"{k}=" for k in _NOT_VARIANT)
        return " ".join(o for o in self.overrides if not o.lstrip("+~").startswith(skip))

    @property
    def variant_key(self) -> tuple[tuple[str, str], ...]:
        """The variant as sorted ``(key, canonical value)`` pairs (for grouping)."""
        return tuple(sorted((k, _canonical(v)) for k, v in self.settings.items()))

    def setting_equals(self, key: str, value: object) -> bool:
        """Whether the job overrides ``key`` with ``value`` (compared after parsing)."""
        return key in self.settings and _canonical(self.settings[key]) == _canonical(value)

    @property
    def sequences(self) -> tuple[str, ...]:
        """The query sequences in ``results.json``, in their order."""
        return tuple(self._sequences())

    def _sequences(self) -> Mapping[str, Mapping[str, object]]:
        sequences = self.results.get("sequences")
        if not isinstance(sequences, Mapping) or not sequences:
            raise ValueError(f"{self.folder / 'results.json'}: no 'sequences' entries")
        return sequences

    def entry(self, sequence: str) -> Mapping[str, object]:
        """``results["sequences"][sequence]``.

        Raises:
            ValueError: the job did not relocalise ``sequence``.
        """
        sequences = self._sequences()
        if sequence not in sequences:
            raise ValueError(
                f"{self.folder / 'results.json'}: no sequence {sequence!r} "
                f"(it has {sorted(sequences)})"
            )
        return sequences[sequence]

    def query_outcomes(self, sequence: str, key: str = "correct") -> tuple[np.ndarray, np.ndarray]:
        """Timestamps and one bool outcome per query of ``<sequence>/queries.json``.

        Args:
            sequence: the query sequence.
            key: the per-query bool field (``correct``: accepted and within 0.3 m).

        Returns:
            ``timestamps`` (Q,) float64 and ``outcomes`` (Q,) bool, in query order.

        Raises:
            FileNotFoundError: no ``queries.json``.
            ValueError: not a list of queries, or a query without a bool ``key`` (results
                written before the key existed: re-run the job).
        """
        path = self.folder / sequence / "queries.json"
        if not path.is_file():
            raise FileNotFoundError(f"{path} is missing: the job did not finish {sequence!r}")
        queries = json.loads(path.read_text())
        if not isinstance(queries, list) or not queries:
            raise ValueError(f"{path}: expected a non-empty list of queries")
        for i, q in enumerate(queries):
            if not isinstance(q.get(key), bool):
                raise ValueError(
                    f"{path}: query {i} has no bool {key!r} (results from before {key!r} was "
                    "added? re-run the job)"
                )
        timestamps = np.array([float(q["timestamp"]) for q in queries])
        return timestamps, np.array([q[key] for q in queries], dtype=bool)


def nested_value(entry: Mapping[str, object], path: Sequence[str], where: str) -> object:
    """``entry[path[0]][path[1]]...``; ``ValueError`` naming the missing key and ``where``."""
    value: object = entry
    for depth, key in enumerate(path):
        if not isinstance(value, Mapping) or key not in value:
            missing = ".".join(path[: depth + 1])
            raise ValueError(
                f"{where}: no {missing!r} in the results (written before {missing!r} was "
                "added? re-run the job)"
            )
        value = value[key]
    return value


def _read_yaml(path: Path) -> object:
    try:
        return yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ValueError(f"{path}: not valid YAML: {exc}") from exc


def _scene_seed(folder: Path, overrides: list[Override]) -> int:
    """``scene.seed`` from the overrides, else from ``.hydra/config.yaml``."""
    for o in overrides:
        if o.key_or_group == _SEED_KEY and not o.is_delete():
            value, where = o.value(), folder / ".hydra" / "overrides.yaml"
            break
    else:
        where = folder / ".hydra" / "config.yaml"
        if not where.is_file():
            raise FileNotFoundError(f"{where} is missing: cannot tell the scene seed of {folder}")
        config = _read_yaml(where)
        scene = config.get("scene") if isinstance(config, Mapping) else None
        value = scene.get("seed") if isinstance(scene, Mapping) else None
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{where}: scene.seed must be an integer, got {value!r}")
    return value


def load_job(folder: str | Path) -> Job:
    """Read one finished job folder (module doc).

    Raises:
        FileNotFoundError: no ``results.json``, or no way to tell the scene seed.
        ValueError: unreadable ``results.json`` or overrides, or a non-integer seed.
    """
    folder = Path(folder)
    results_path = folder / "results.json"
    if not results_path.is_file():
        raise FileNotFoundError(f"{results_path} is missing: the job did not finish")
    try:
        results = json.loads(results_path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{results_path}: not valid JSON: {exc}") from exc
    overrides_path = folder / ".hydra" / "overrides.yaml"
    lines = _read_yaml(overrides_path) if overrides_path.is_file() else []
    if not isinstance(lines, list) or not all(isinstance(x, str) for x in lines):
        raise ValueError(f"{overrides_path}: expected a list of override strings")
    lines = [x for x in lines if not x.lstrip("+~").startswith("hydra.")]
    parsed = _parse_overrides(lines, overrides_path)
    settings = {
        o.key_or_group: o.value()
        for o in parsed
        if o.key_or_group not in _NOT_VARIANT and not o.is_delete()
    }
    return Job(folder, _scene_seed(folder, parsed), tuple(lines), settings, results)


def _expected_jobs(multirun: Path) -> int | None:
    """Jobs a sweep launches, from the sweep overrides in ``multirun.yaml`` (None: unknown)."""
    config = _read_yaml(multirun)
    hydra = config.get("hydra") if isinstance(config, Mapping) else None
    if not isinstance(hydra, Mapping):
        raise ValueError(f"{multirun}: no 'hydra' node")
    params = (hydra.get("sweeper") or {}).get("params")
    if params:  # sweeps declared in the config: not counted here
        return None
    lines = (hydra.get("overrides") or {}).get("task") or []
    overrides = _parse_overrides(lines, multirun)
    sizes = [len(list(o.sweep_string_iterator())) for o in overrides if o.is_sweep_override()]
    return math.prod(sizes)


def _sweep_job_folders(sweep: Path) -> list[Path]:
    """The numbered job folders of a finished sweep, in job order.

    Raises:
        ValueError: a half-finished sweep: fewer finished jobs than ``multirun.yaml``
            describes, extra job folders (a reused sweep folder), or job folders without
            ``results.json``.
    """
    folders = sorted(
        (p for p in sweep.iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name)
    )
    unfinished = [p.name for p in folders if not (p / "results.json").is_file()]
    multirun = sweep / "multirun.yaml"
    expected = _expected_jobs(multirun) if multirun.is_file() else None
    if expected is not None and len(folders) != expected:
        raise ValueError(
            f"{sweep}: {len(folders)} job folders but {multirun.name} describes {expected} jobs "
            "(a half-finished sweep, or a sweep folder reused by another sweep)"
        )
    if unfinished:
        raise ValueError(
            f"{sweep}: half-finished sweep, jobs {', '.join(unfinished)} of {len(folders)} have "
            "no results.json"
        )
    if not folders:
        raise ValueError(f"{sweep}: an empty sweep folder (no numbered job folders)")
    return folders


def load_jobs(paths: Iterable[str | Path]) -> list[Job]:
    """All jobs of some job folders and sweep folders, in the given order.

    Args:
        paths: job folders (with ``results.json``) and/or sweep folders (with
            ``multirun.yaml`` or numbered job folders).

    Returns:
        One :class:`Job` per finished job.

    Raises:
        FileNotFoundError: a path that does not exist.
        ValueError: no paths, a folder that is neither a job nor a sweep, or an empty or
            half-finished sweep.
    """
    jobs = []
    paths = [Path(p) for p in paths]
    if not paths:
        raise ValueError("no run or sweep folders given")
    for path in paths:
        if not path.is_dir():
            raise FileNotFoundError(f"{path} is not a folder")
        if (path / "results.json").is_file():
            jobs.append(load_job(path))
        elif (path / "multirun.yaml").is_file() or any(
            p.is_dir() and p.name.isdigit() for p in path.iterdir()
        ):
            jobs += [load_job(p) for p in _sweep_job_folders(path)]
        else:
            raise ValueError(
                f"{path}: neither a job folder (results.json) nor a sweep folder "
                "(multirun.yaml, numbered job folders); is the run still going?"
            )
    return jobs


@dataclass(frozen=True)
class VariantJobs:
    """The jobs of one variant, one per scene seed, sorted by seed.

    Attributes:
        variant: the variant's overrides as written (``""`` for the defaults).
        jobs: the jobs, in increasing seed order.
    """

    variant: str
    jobs: tuple[Job, ...]

    @property
    def seeds(self) -> tuple[int, ...]:
        """The scene seeds, increasing."""
        return tuple(j.seed for j in self.jobs)

    @property
    def settings(self) -> Mapping[str, object]:
        """The variant's settings (the same for every job)."""
        return self.jobs[0].settings

    def by_seed(self) -> dict[int, Job]:
        """Seed -> job."""
        return {j.seed: j for j in self.jobs}


def group_variants(jobs: Sequence[Job]) -> list[VariantJobs]:
    """Group jobs by variant (first-seen order), one job per seed.

    Raises:
        ValueError: no jobs, or two jobs of one variant on the same seed (named).
    """
    if not jobs:
        raise ValueError("no jobs to group")
    groups: dict[tuple, list[Job]] = {}
    for job in jobs:
        groups.setdefault(job.variant_key, []).append(job)
    out = []
    for members in groups.values():
        seen: dict[int, Job] = {}
        for job in members:
            if job.seed in seen:
                raise ValueError(
                    f"two jobs of variant {job.variant!r} on scene seed {job.seed}: "
                    f"{seen[job.seed].folder} and {job.folder}"
                )
            seen[job.seed] = job
        out.append(VariantJobs(members[0].variant, tuple(sorted(members, key=lambda j: j.seed))))
    return out


def check_held_out(jobs: Sequence[Job], tuning_seeds: Iterable[int] = (0,)) -> None:
    """Refuse jobs on a tuning seed (results are reported on held-out seeds only).

    Raises:
        ValueError: a job whose scene seed is a tuning seed (the folders are named).
    """
    tuning = set(tuning_seeds)
    bad = [f"{j.folder} (seed {j.seed})" for j in jobs if j.seed in tuning]
    if bad:
        raise ValueError(
            f"scene seeds {sorted(tuning)} were used for tuning; not held out: {', '.join(bad)}"
        )

"""Score finished relocalisation jobs again under today's pose-validation settings.

For the given job folder, or every job of the given sweep folder, the validation settings are
composed from today's ``conf/`` with the job's own overrides (so ``scene=outdoor`` jobs get the
outdoor thresholds) plus any ``--set`` overrides, and the job is written again into ``--out``
(a sweep keeps its numbered job folders) by :func:`diffloc.pipeline.revalidate.revalidate_run`:
same poses, new verdicts and figures. Held-out reports read the result like any sweep.

Usage:
    python3 experiments/revalidate.py experiments/runs/heldout_main \\
        --out experiments/runs/heldout_main_revalidated
"""

from __future__ import annotations

import argparse
from pathlib import Path

import yaml
from hydra import compose, initialize_config_dir

from diffloc.cli import CONF_DIR
from diffloc.config import to_object
from diffloc.eval.sweeps import load_jobs
from diffloc.pipeline.revalidate import revalidate_run
from diffloc.reloc.validation import ValidationConfig


def validation_config(job: Path, extra: list[str]) -> ValidationConfig:
    """Today's ``reloc.validation`` for the job's overrides (``hydra.*`` left out)."""
    lines = yaml.safe_load((job / ".hydra" / "overrides.yaml").read_text()) or []
    overrides = [x for x in lines if not x.lstrip("+~").startswith("hydra.")] + extra
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    return to_object(cfg.reloc).validation


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run", type=Path, help="a job or sweep folder")
    parser.add_argument("--out", type=Path, required=True, help="folder to write the jobs into")
    parser.add_argument(
        "--set", action="append", default=[], help="extra override, e.g. reloc.validation.x=1"
    )
    args = parser.parse_args(argv)
    for job in load_jobs([args.run]):
        dst = args.out if job.folder == args.run else args.out / job.folder.name
        revalidate_run(job.folder, dst, validation_config(job.folder, args.set))
        print(f"{job.folder} -> {dst}")


if __name__ == "__main__":
    main()

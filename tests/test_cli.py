"""The Hydra app: every config composes into typed objects; bad input gets clear errors."""

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf
from omegaconf.errors import ConfigKeyError, ValidationError

from diffloc.cli import TASKS, _show_warning, run
from diffloc.config import CONF_DIR, UnknownKeyError, register_configs, to_object
from diffloc.pipeline.hints import MissingStageError
from diffloc.sim.config import IndoorSceneConfig, OutdoorSceneConfig
from tests.conftest import TINY, compose_config

ROOT = Path(__file__).resolve().parents[1]


def _diffloc(
    *args: str, cwd: Path, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    """Run ``python -m diffloc.cli ARGS`` in ``cwd`` (with this checkout's package)."""
    return subprocess.run(
        [sys.executable, "-m", "diffloc.cli", *args],
        capture_output=True,
        text=True,
        env={**os.environ, "CI": "true", "PYTHONPATH": str(ROOT), **(env or {})},
        cwd=cwd,
        timeout=600,
    )


@pytest.mark.parametrize(
    ("scene", "schema"), [("indoor", IndoorSceneConfig), ("outdoor", OutdoorSceneConfig)]
)
def test_every_scene_config_composes_into_its_schema(scene, schema):
    cfg = compose_config([f"scene={scene}", "task=simulate"])
    obj = OmegaConf.to_object(cfg.scene)
    assert isinstance(obj, schema)
    assert [s.name for s in obj.sequences] == [
        "mapping",
        "query_same",
        "query_lane",
        "query_reverse",
        "changed",
    ]
    assert cfg.out_dir == f"data/{scene}_seed0"


def test_unknown_scene_name_lists_the_choices():
    with pytest.raises(ConfigCompositionException, match="indoor"):
        compose_config(["scene=moon_base"])


def test_unknown_task_lists_tasks_not_schemas():
    with pytest.raises(ConfigCompositionException) as error:
        compose_config(["task=mian"])
    options = str(error.value).split("Available options in 'task':")[1].split("Config search")[0]
    assert options.split() == sorted(TASKS)


def test_help_lists_the_tasks_and_no_schema(tmp_path):
    done = _diffloc("--help", cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.startswith("diffloc:")
    groups = dict(
        line.split(": ", 1) for line in done.stdout.splitlines() if line.startswith("task: ")
    )
    assert groups["task"].split(", ") == sorted(TASKS)
    assert "schema" not in done.stdout


def test_non_integer_seed_is_refused():
    with pytest.raises((ValidationError, ConfigCompositionException)):
        OmegaConf.to_object(compose_config(["scene.seed=abc"]).scene)


def test_misspelt_key_is_refused():
    with pytest.raises((ConfigKeyError, ConfigCompositionException)):
        compose_config(["scene.camera.widht=100"])


@pytest.mark.parametrize(
    ("override", "advice"),
    [
        ("+scene.max_frames=5", "scene.trajectory.max_frames"),
        ("+db.features.max_keypoint=500", "db.features.max_keypoints"),
        ("+reloc.retriever.cluster=64", "reloc.retriever.clusters"),
        ("+scene.sequences.1.speed=2", "speed_mps"),
        ("+task.outdir=x", "task.out_dir"),
        ("++scene.camera.widht=100", "scene.camera.width"),
        ("+frames=5", "the keys of the root"),
    ],
)
def test_unknown_key_added_with_plus_is_refused(override, advice):
    with pytest.raises(UnknownKeyError, match=f"unknown config key .*{re.escape(advice)}"):
        compose_config([override])


def test_run_refuses_a_config_with_an_unknown_key(tmp_path):
    register_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["+scene.max_frames=5"])
    with pytest.raises(UnknownKeyError, match="scene.max_frames"):
        run(cfg)


def test_console_script_simulates_a_dataset(tmp_path):
    out = tmp_path / "ds"
    args = ["task=simulate", "scene=indoor", "scene.seed=2", f"out_dir={out}"]
    args += [a for a in TINY if not a.startswith("scene.trajectory")]
    args += ["scene.trajectory.max_frames=2", f"hydra.run.dir={tmp_path / 'run'}"]
    env = {**os.environ, "CI": "true"}
    done = subprocess.run(
        [sys.executable, "-m", "diffloc.cli", *args],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"dataset: {out}" in done.stdout
    assert (out / "preview.png").exists()
    assert len(list((out / "mapping" / "rgb").glob("*.png"))) == 2


@pytest.mark.parametrize(
    "task",
    [
        "simulate",
        "build_map",
        "build_db",
        "optimize_db",
        "update_db",
        "relocalize",
        "export_colmap",
        "main",
        "train_nerf",
        "crossmodal",
    ],
)
@pytest.mark.parametrize("scene", ["indoor", "outdoor"])
def test_every_task_config_composes_into_typed_objects(task, scene):
    cfg = to_object(compose_config([f"task={task}", f"scene={scene}"]))
    assert cfg.task.name == task
    assert cfg.reloc.validation.theta_in == 15
    assert cfg.reloc.validation.theta_dist_m == (0.3 if scene == "indoor" else 0.8)
    assert (cfg.reloc.method.top_k, cfg.reloc.method.n_max, cfg.reloc.method.n_co) == (30, 3, 5)


def test_the_default_task_is_the_main_job():
    assert compose_config([]).task.name == "main"


def test_relocalize_without_a_database_says_which_task_to_run(tiny_indoor_dataset):
    with pytest.raises(MissingStageError, match="task=build_db"):
        run(compose_config(["task=relocalize", f"dataset={tiny_indoor_dataset}"]))


def test_a_task_without_a_dataset_says_how_to_simulate_it(tmp_path):
    with pytest.raises(MissingStageError, match=f"task=simulate out_dir={tmp_path}` first"):
        run(compose_config(["task=build_map", f"dataset={tmp_path}"]))


@pytest.mark.parametrize(
    ("case", "expected"),
    [
        ("no_dataset", "missing: run `diffloc task=simulate scene=outdoor dataset={data} "),
        ("bad_seed", "error: seed must be a non-negative integer, got -1"),
        (
            "no_database",
            "build_db.json is missing: run `diffloc task=build_db scene=outdoor "
            "dataset={data} db.noise_sigma=0.3 reloc.database=database` first",
        ),
        ("unknown_key", "unknown config key scene.max_frames"),
        (
            "wrong_map",
            "error: task=main cannot use map=tls: task=crossmodal takes map=tls, map=cloud, "
            "map=mesh, map=images, map=nerf or map=hybrid; every other task takes map=surfel",
        ),
        (
            "images_no_surfels",
            "build_map.json is missing: run `diffloc task=build_map dataset={data}`",
        ),
    ],
)
def test_a_checked_error_prints_one_line_with_the_users_overrides(
    case, expected, tiny_indoor_dataset, tmp_path
):
    data = {"no_dataset": tmp_path / "nothing"}.get(case, tiny_indoor_dataset)
    if case == "images_no_surfels":  # reading the map takes its lock: not in the shared dataset
        data = Path(shutil.copytree(data, tmp_path / data.name))
    args = {
        "no_dataset": ["task=build_map", "scene=outdoor", f"dataset={data}"],
        "bad_seed": ["task=simulate", "scene.seed=-1", f"out_dir={tmp_path / 'sim'}"],
        "no_database": [
            "task=relocalize",
            "scene=outdoor",
            f"dataset={data}",
            "db.noise_sigma=0.3",
            "reloc.database=database",
            f"task.out_dir={tmp_path / 'reloc'}",
        ],
        "unknown_key": ["+scene.max_frames=5", f"out_dir={tmp_path / 'sim'}"],
        "wrong_map": ["task=main", "map=tls", f"out_dir={tmp_path / 'sim'}"],
        # the hint names task=build_map without the map option it cannot use
        "images_no_surfels": ["task=crossmodal", "map=images", "map.every=3", f"dataset={data}"],
    }[case]
    done = _diffloc(*args, f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert done.returncode == 1
    assert done.stderr.count("\n") == 1 and done.stderr.startswith("error: "), done.stderr
    assert expected.format(data=data) in done.stderr
    assert not (tmp_path / "sim").exists()  # nothing simulated


def test_warnings_print_one_line_each(capsys):
    _show_warning(UserWarning("the check rejected it"), UserWarning, "x.py", 3, None, "code")
    assert capsys.readouterr().err == "warning: the check rejected it\n"


def test_hydra_full_error_shows_the_traceback(tmp_path):
    done = _diffloc(
        "task=build_map",
        f"dataset={tmp_path}",
        f"hydra.run.dir={tmp_path / 'run'}",
        cwd=tmp_path,
        env={"HYDRA_FULL_ERROR": "1"},
    )
    assert done.returncode == 1
    assert "Traceback" in done.stderr and "MissingStageError" in done.stderr

"""Error messages that name a command: the user's overrides replace the stage's selection."""

from __future__ import annotations

import pytest

from diffloc.pipeline.hints import (
    Command,
    ExistingOutputError,
    MissingStageError,
    StaleStageError,
    override_key,
)


def test_override_keys():
    assert override_key("db.noise_sigma=0.2") == "db.noise_sigma"
    assert override_key("+scene.trajectory.max_frames=5") == "scene.trajectory.max_frames"
    assert override_key("~task.out_dir") == "task.out_dir"
    assert override_key("task=main") == "task"


def test_command_uses_the_users_overrides_and_its_own_settings():
    command = Command("update_db", ("dataset=d",), ("task.sequence=query_lane",))
    assert command.line() == "diffloc task=update_db dataset=d task.sequence=query_lane"
    users = ["scene=outdoor", "dataset=d", "task.sequence=changed"]
    assert command.line(users) == (
        "diffloc task=update_db scene=outdoor dataset=d task.sequence=query_lane"
    )
    quoted = Command("main").line(["db.pose_prior_sigma_m=${db.noise_sigma}"])
    assert quoted == "diffloc task=main 'db.pose_prior_sigma_m=${db.noise_sigma}'"


@pytest.mark.parametrize(
    ("error", "kind", "message"),
    [
        (
            MissingStageError("d/map/surfel_map.ply", Command("build_map", ("dataset=d",))),
            FileNotFoundError,
            "d/map/surfel_map.ply is missing: run `diffloc task=build_map dataset=d` first",
        ),
        (
            ExistingOutputError("out is not empty", Command("x", (), ("task.overwrite=true",))),
            FileExistsError,
            "out is not empty; to replace it: `diffloc task=x task.overwrite=true`",
        ),
        (
            StaleStageError("record lists 3 keyframes", Command("build_db")),
            ValueError,
            "record lists 3 keyframes: make it again with `diffloc task=build_db`",
        ),
    ],
)
def test_errors_keep_their_builtin_kind(error, kind, message):
    assert isinstance(error, kind)
    assert str(error) == message
    assert error.render(["scene=outdoor"]).count("scene=outdoor") == 1

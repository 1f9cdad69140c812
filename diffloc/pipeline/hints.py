"""Errors whose message names the ``diffloc`` command that fixes them.

A stage that finds an input missing (no surfel map, no database) says which task makes it:
``.../build_db.json is missing: run `diffloc task=build_db dataset=data/x db.noise_sigma=0.2`
first``. The command must select the same dataset and database as the run that failed. The
stage knows only its config, so it names the overrides that select them (the
:attr:`Command.selection`); the ``diffloc`` command knows what the user typed and renders the
message again with the user's own overrides in their place (:meth:`CommandHint.render`), so
``scene=outdoor`` or ``db.pose_prior_sigma_m=0.2`` carry over even where no stage reads them.

Example:
    >>> error = MissingStageError("x/map/surfel_map.ply", Command("build_map", ("dataset=x",)))
    >>> str(error)
    'x/map/surfel_map.ply is missing: run `diffloc task=build_map dataset=x` first'
    >>> error.render(["scene=outdoor", "dataset=x"])
    'x/map/surfel_map.ply is missing: run `diffloc task=build_map scene=outdoor dataset=x` first'
"""

from __future__ import annotations

import shlex
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

__all__ = [
    "Command",
    "CommandHint",
    "ExistingOutputError",
    "MissingStageError",
    "StaleStageError",
    "override_key",
]

PLACEHOLDER = "{command}"
"""Where a hint's message template takes the command line."""


def override_key(override: str) -> str:
    """The key an override sets: ``"db.noise_sigma"`` of ``"+db.noise_sigma=0.2"``."""
    return override.split("=", 1)[0].lstrip("+~")


@dataclass(frozen=True)
class Command:
    """A ``diffloc`` command line named by an error message.

    Attributes:
        task: the task to run.
        selection: overrides that select the failed run's dataset and database folder, as the
            stage can tell them from its config (e.g. ``("dataset=data/x",
            "db.noise_sigma=0.2")``); replaced by the user's own overrides where known.
        settings: overrides the fix needs whatever the user typed (e.g.
            ``("task.sequence=query_lane",)``, ``("task.overwrite=true",)``).
    """

    task: str
    selection: tuple[str, ...] = ()
    settings: tuple[str, ...] = ()

    def line(self, overrides: Sequence[str] | None = None) -> str:
        """The shell-quoted command line.

        Args:
            overrides: the user's own overrides, used instead of :attr:`selection` (those that
                set a key of :attr:`settings` are left out); ``None``: :attr:`selection`.
        """
        chosen = self.selection if overrides is None else overrides
        fixed = {override_key(s) for s in self.settings}
        words = [w for w in chosen if override_key(w) not in fixed]
        return shlex.join(["diffloc", f"task={self.task}", *words, *self.settings])


class CommandHint(Exception):
    """Base of errors whose message names a :class:`Command` (module docstring).

    Args:
        template: the message, with ``{command}`` where the command line goes.
        command: the command.
    """

    def __init__(self, template: str, command: Command) -> None:
        self.template = template
        self.command = command
        super().__init__(self.render())

    def render(self, overrides: Sequence[str] | None = None) -> str:
        """The message with the command given ``overrides`` (see :meth:`Command.line`)."""
        return self.template.replace(PLACEHOLDER, f"`{self.command.line(overrides)}`")


class MissingStageError(CommandHint, FileNotFoundError):
    """An input of a stage is missing; the task that makes it must run first.

    Attributes:
        path: the missing file or folder.
    """

    def __init__(self, path: str | Path, command: Command) -> None:
        self.path = Path(path)
        super().__init__(f"{path} is missing: run {PLACEHOLDER} first", command)


class ExistingOutputError(CommandHint, FileExistsError):
    """An output is in the way; the command (with an overwrite setting) replaces it."""

    def __init__(self, reason: str, command: Command) -> None:
        super().__init__(f"{reason}; to replace it: {PLACEHOLDER}", command)


class StaleStageError(CommandHint, ValueError):
    """A stage's saved output does not match its record; the command makes it again."""

    def __init__(self, reason: str, command: Command) -> None:
        super().__init__(f"{reason}: make it again with {PLACEHOLDER}", command)

"""The ``nerf`` node: the settings of training one radiance-field submap (``task=train_nerf``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from diffloc.maps.nerf.data import SubmapDataConfig
from diffloc.maps.nerf.module import NerfTrainConfig
from diffloc.maps.nerf.submaps import SubmapConfig

__all__ = ["TrainNerfConfig"]


@dataclass
class TrainNerfConfig:
    """The root ``nerf`` node: cluster the mapping run into submaps and train submap ``submap``
    (``diffloc task=train_nerf nerf.submap=3``; all of them with
    ``diffloc -m task=train_nerf nerf.submap=0,1,2,3``).

    Attributes:
        submap: which submap to train (index into the clustering).
        sequence: the mapping sequence of the dataset.
        out_dir: run folder; empty: ``<dataset>/nerf``.
        epochs: train until this many epochs of ``train.steps_per_epoch`` steps.
        resume: continue from the submap's last checkpoint if there is one.
        submaps: trajectory clustering settings.
        data: training-ray settings.
        train: field, sampler, loss and optimiser settings.
    """

    submap: int = 0
    sequence: str = "mapping"
    out_dir: str = ""
    epochs: int = 30
    resume: bool = True
    submaps: SubmapConfig = field(default_factory=lambda: SubmapConfig(num_submaps=4))
    data: SubmapDataConfig = field(default_factory=SubmapDataConfig)
    train: NerfTrainConfig = field(default_factory=NerfTrainConfig)

    def __post_init__(self) -> None:
        for name, low in (("submap", 0), ("epochs", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ValueError(f"nerf.{name} must be an integer >= {low}, got {value!r}")

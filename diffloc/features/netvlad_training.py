"""Fine-tuning a NetVLAD layer with the triplet ranking loss on posed database images.

Training pairs come from ground-truth poses, not labels: a *positive* of an anchor frame is a
frame within 1 m and 30 degrees (an overlapping view), a *negative* a frame more than 5 m
away. The loss is NetVLAD's (Arandjelovic et al. 2016, Eq. 7 with squared distances):
``sum_j max(0, margin + ||f(a) - f(p)||^2 - ||f(a) - f(n_j)||^2)`` over the negatives
``n_j``, so only negatives that violate the margin contribute. As in the paper, tuples are
re-mined from the current descriptors at the start of every epoch: the positive is the
best-matching frame among the potential positives and the negatives are the hardest (most
similar) frames among all negatives (random negatives almost never violate the margin, which
leaves nothing to learn). The dense descriptor
backbone stays frozen: the training set holds precomputed (D, h, w) maps and only the NetVLAD
parameters (assignment conv and centroids) are learned.

Across domains (real images and renders of a map, say) each frame carries a domain label and
the positives and negatives of an anchor are taken from the other domains only, so the layer
learns to rank renders for a real image (and real images for a render) rather than within one
kind of image.

Example::

    netvlad = NetVLAD(num_clusters=64, dim=64)
    netvlad.init_from_kmeans(sampled_descriptors, torch.Generator().manual_seed(0))
    result = finetune_netvlad(netvlad, features, T_wc, FinetuneConfig(epochs=3), seed=0)
    result.initial_loss, result.final_loss
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset

from diffloc.checks import ShapeError, check_positive_int, check_shape
from diffloc.features.global_ import NetVLAD
from diffloc.features.retrieval_eval import pairwise_pose_distances
from diffloc.progress import progress_enabled

__all__ = [
    "FinetuneConfig",
    "FinetuneResult",
    "NetVLADFineTuner",
    "TripletConfig",
    "TripletDataset",
    "finetune_netvlad",
]


@dataclass
class TripletConfig:
    """How positives and negatives are chosen from poses.

    Attributes:
        positive_distance_m: largest camera-centre distance of a positive.
        positive_angle_deg: largest relative rotation angle of a positive.
        negative_distance_m: smallest camera-centre distance of a negative.
        num_negatives: negatives per anchor (with replacement when fewer exist).
        hard_mining: re-mine best positives and hardest negatives every epoch; otherwise
            keep the random tuples drawn at construction.
    """

    positive_distance_m: float = 1.0
    positive_angle_deg: float = 30.0
    negative_distance_m: float = 5.0
    num_negatives: int = 5
    hard_mining: bool = True


@dataclass
class FinetuneConfig:
    """Optimisation settings of :func:`finetune_netvlad`.

    Attributes:
        epochs: passes over the anchors.
        batch_size: anchors per step.
        learning_rate: Adam step size.
        margin: triplet margin on squared descriptor distances (the paper's m = 0.1).
        triplets: positive/negative mining settings.
    """

    epochs: int = 5
    batch_size: int = 8
    learning_rate: float = 1e-3
    margin: float = 0.1
    triplets: TripletConfig = field(default_factory=TripletConfig)


class TripletDataset(Dataset):
    """(anchor, positive, negatives) tuples of dense maps, chosen from poses.

    Anchors are the frames with at least one positive and one negative. Tuples start random
    (from ``seed``: a uniformly random positive and ``num_negatives`` random negatives);
    :meth:`mine` replaces them by the best positive and hardest negatives under a model.

    Args:
        features: (N, D, h, w) dense descriptor maps of the database frames (any float dtype;
            items are returned as float32).
        T_wc: (N, 4, 4) camera-to-world poses of the same frames.
        config: mining thresholds.
        seed: seed of the sampling.
        domains: (N,) int64 domain of each frame (e.g. 0 real image, 1 render): positives and
            negatives come from another domain than their anchor's; ``None``: one domain.

    Raises:
        ShapeError: mismatched shapes.
        ValueError: no frame has both a positive and a negative, ``num_negatives`` < 1.
    """

    def __init__(
        self,
        features: torch.Tensor,
        T_wc: torch.Tensor,
        config: TripletConfig,
        seed: int = 0,
        domains: torch.Tensor | None = None,
    ) -> None:
        check_shape(features, "N,D,h,w", "features")
        check_shape(T_wc, "N,4,4", "T_wc")
        if len(features) != len(T_wc):
            raise ShapeError(f"{len(features)} feature maps but {len(T_wc)} poses")
        if domains is not None:
            check_shape(domains, f"{len(features)}", "domains")
        self.features = features
        self.num_negatives = check_positive_int(config.num_negatives, "num_negatives")
        distance, angle = pairwise_pose_distances(T_wc, T_wc)
        positive = (distance <= config.positive_distance_m) & (
            angle <= math.radians(config.positive_angle_deg)
        )
        positive.fill_diagonal_(False)
        negative = distance > config.negative_distance_m
        if domains is not None:
            across = domains[:, None] != domains[None, :]
            positive &= across
            negative &= across
        self.anchors = torch.nonzero(positive.any(1) & negative.any(1)).flatten()
        if not len(self.anchors):
            raise ValueError("no frame has both a positive and a negative; check the thresholds")
        self.positive = positive[self.anchors]  # (A, N)
        self.negative = negative[self.anchors]  # (A, N)
        generator = torch.Generator().manual_seed(seed)
        pos = torch.multinomial(self.positive.double(), 1, generator=generator)
        neg = torch.multinomial(
            self.negative.double(), self.num_negatives, replacement=True, generator=generator
        )
        self.tuples = torch.cat([self.anchors[:, None], pos, neg], dim=1)

    @torch.no_grad()
    def mine(self, netvlad: NetVLAD, batch_size: int = 16) -> None:
        """Re-choose each anchor's best-matching positive and hardest negatives.

        Args:
            netvlad: the model whose :meth:`NetVLAD.aggregate` descriptors rank the frames.
            batch_size: maps per forward pass.
        """
        embedding = torch.cat(
            [netvlad.aggregate(chunk.float()) for chunk in self.features.split(batch_size)]
        )
        similarity = embedding[self.anchors] @ embedding.T  # (A, N)
        pos = similarity.masked_fill(~self.positive, -math.inf).argmax(1, keepdim=True)
        hardest = similarity.masked_fill(~self.negative, -math.inf)
        k = min(self.num_negatives, int(self.negative.sum(1).min()))
        neg = torch.topk(hardest, k, dim=1).indices
        neg = neg[:, torch.arange(self.num_negatives) % k]  # repeat when fewer negatives
        self.tuples = torch.cat([self.anchors[:, None], pos, neg], dim=1)

    def __len__(self) -> int:
        return len(self.tuples)

    def __getitem__(self, i: int) -> torch.Tensor:
        """(2 + num_negatives, D, h, w): anchor, positive, negatives."""
        return self.features[self.tuples[i]].float()


class NetVLADFineTuner(L.LightningModule):
    """Lightning module training a :class:`NetVLAD` layer with the triplet ranking loss.

    Args:
        netvlad: the layer to train (updated in place).
        margin: triplet margin on squared distances.
        learning_rate: Adam step size.
        miner: a dataset to re-mine (:meth:`TripletDataset.mine`) at every epoch start, or
            ``None`` to keep its tuples.
    """

    def __init__(
        self,
        netvlad: NetVLAD,
        margin: float = 0.1,
        learning_rate: float = 1e-3,
        miner: TripletDataset | None = None,
    ):
        super().__init__()
        self.netvlad = netvlad
        self.margin = margin
        self.learning_rate = learning_rate
        self.miner = miner
        self.epoch_losses: list[float] = []
        self._step_losses: list[float] = []

    def triplet_loss(self, batch: torch.Tensor) -> torch.Tensor:
        """Mean over anchors of the summed hinge losses of their negatives.

        Args:
            batch: (B, 2 + n, D, h, w) anchor, positive and n negative maps per row.

        Returns:
            () loss.
        """
        check_shape(batch, "B,T,D,h,w", "batch")
        b, t = batch.shape[:2]
        embedding = self.netvlad.aggregate(batch.flatten(0, 1)).view(b, t, -1)
        anchor, positive, negatives = embedding[:, 0], embedding[:, 1], embedding[:, 2:]
        d_pos = (anchor - positive).pow(2).sum(-1)
        d_neg = (anchor[:, None] - negatives).pow(2).sum(-1)
        return torch.relu(self.margin + d_pos[:, None] - d_neg).sum(1).mean()

    def on_train_epoch_start(self) -> None:
        if self.miner is not None:
            self.miner.mine(self.netvlad)

    def training_step(self, batch: torch.Tensor, batch_idx: int) -> torch.Tensor:
        loss = self.triplet_loss(batch)
        self._step_losses.append(float(loss.detach()))
        self.log("train_loss", loss, prog_bar=True, batch_size=len(batch))
        return loss

    def on_train_epoch_end(self) -> None:
        self.epoch_losses.append(sum(self._step_losses) / max(len(self._step_losses), 1))
        self._step_losses.clear()

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(self.netvlad.parameters(), lr=self.learning_rate)


@dataclass
class FinetuneResult:
    """What :func:`finetune_netvlad` did.

    Attributes:
        epoch_losses: mean training loss of each epoch.
        initial_loss: mean loss over all tuples before training (tuples mined with the initial
            model when hard mining is on).
        final_loss: mean loss over all tuples after training (re-mined with the final model).
        num_tuples: training tuples (anchors).
    """

    epoch_losses: list[float]
    initial_loss: float
    final_loss: float
    num_tuples: int


@torch.no_grad()
def _mean_loss(module: NetVLADFineTuner, dataset: TripletDataset, batch_size: int) -> float:
    loader = DataLoader(dataset, batch_size=batch_size, shuffle=False)
    total = sum(float(module.triplet_loss(batch)) * len(batch) for batch in loader)
    return total / len(dataset)


def finetune_netvlad(
    netvlad: NetVLAD,
    features: torch.Tensor,
    T_wc: torch.Tensor,
    config: FinetuneConfig | None = None,
    seed: int = 0,
    show_progress: bool = True,
    domains: torch.Tensor | None = None,
) -> FinetuneResult:
    """Fine-tune ``netvlad`` in place with a CPU ``lightning.Trainer``.

    Deterministic given ``seed`` (tuple sampling and shuffling use their own generators; no
    global random state is touched). The progress bar is off when ``CI=true``.

    Args:
        netvlad: an initialised layer (e.g. by :meth:`NetVLAD.init_from_kmeans`).
        features: (N, D, h, w) dense maps of the database frames.
        T_wc: (N, 4, 4) poses of the database frames.
        config: optimisation settings (defaults: :class:`FinetuneConfig`).
        seed: seed of tuple sampling and batch order.
        show_progress: show Lightning's progress bar (unless in CI).
        domains: (N,) domain of each frame; tuples cross domains (:class:`TripletDataset`).

    Returns:
        Loss history and the loss over all tuples before and after training.
    """
    config = config or FinetuneConfig()
    dataset = TripletDataset(features, T_wc, config.triplets, seed, domains)
    miner = dataset if config.triplets.hard_mining else None
    module = NetVLADFineTuner(netvlad, config.margin, config.learning_rate, miner)
    if miner is not None:
        miner.mine(netvlad)
    initial = _mean_loss(module, dataset, config.batch_size)
    loader = DataLoader(
        dataset,
        batch_size=config.batch_size,
        shuffle=True,
        generator=torch.Generator().manual_seed(seed),
    )
    trainer = L.Trainer(
        accelerator="cpu",
        devices=1,
        max_epochs=config.epochs,
        logger=False,
        enable_checkpointing=False,
        enable_model_summary=False,
        enable_progress_bar=progress_enabled(show_progress),
        num_sanity_val_steps=0,
    )
    trainer.fit(module, loader)
    netvlad.eval()
    if miner is not None:
        miner.mine(netvlad)
    return FinetuneResult(
        epoch_losses=list(module.epoch_losses),
        initial_loss=initial,
        final_loss=_mean_loss(module, dataset, config.batch_size),
        num_tuples=len(dataset),
    )

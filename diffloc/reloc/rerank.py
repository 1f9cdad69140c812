"""Re-ranking retrieved database images by mutual-nearest-neighbour descriptor matches.

A second retrieval stage (beyond seed 2) between the global retrieval (NetVLAD) and the costly
LighterGlue + PnP: the ``K`` images the global descriptor ranks highest are re-ranked by how
many of their local descriptors are mutual nearest neighbours of the query's, counted in one
batched product against the database's cached XFeat descriptors. Only the ``n`` strongest
keypoints (detector score) of the query and of each image take part, so one re-ranking costs
``K n^2 D`` multiply-adds (50 x 512^2 x 64 = 0.84 G: about 0.2 s on one core).

For the query descriptors ``q`` (n, D) and one image's ``d`` (m, D), both L2-normalised, the
similarity is ``S = q d^T`` (n, m); query keypoint ``i`` and image keypoint ``j`` match when
``j = argmax_j' S[i, j']``, ``i = argmax_i' S[i', j]`` and ``S[i, j] > min_similarity``. The
score of the image is its number of matches; ties keep the global order (stable sort).

Example:
    >>> d = torch.eye(3)  # 3 unit descriptors: image 0 holds the first two, image 1 the last
    >>> reranker = MutualNNReranker([d[:2], d[2:]], [torch.ones(2), torch.ones(1)], RerankConfig())
    >>> scores, order = reranker.rerank(d[2:3], torch.tensor([0, 1]))  # the query is d[2]
    >>> scores.tolist(), order.tolist()
    ([1, 0], [1, 0])
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from diffloc.checks import check_positive_int, check_shape

__all__ = ["MutualNNReranker", "RerankConfig", "mutual_nn_counts"]


@dataclass(frozen=True)
class RerankConfig:
    """Settings of :class:`MutualNNReranker`.

    The defaults were chosen on indoor seed 0 only (TLS cloud, single-pass renders, 320x240,
    every 4th frame of ``query_same`` / ``query_lane`` / ``query_reverse``, 31 / 35 / 33
    queries); figures are the share of queries whose right render (within 2 m and 45 deg) is
    ranked first / in the first 3 / in the first 5, per sequence, and the median CPU ms of one
    re-ranking (one core, under load 8-12):

    - NetVLAD alone: 23 / 42 / 48 % (same), 23 / 26 / 34 % (lane), 21 / 27 / 27 % (reverse);
    - ``candidates=50, keypoints=512``: 52 / 61 / 65 %, 34 / 46 / 49 %, 27 / 36 / 42 %, 170 ms;
    - ``candidates`` 30 / 80: about the same ranks (48-52 % first on same) at 70 / 300 ms;
    - ``keypoints`` 1024: 55 / 61 / 65 %, 37 / 49 / 51 %, 30 / 39 / 48 % but 800 ms; 256:
      29 / 45 / 55 % on same at 17 ms (too few shared keypoints);
    - ``min_similarity=0.8``: 52 / 58 / 68 %, 40 / 51 / 54 %, 21 / 33 / 45 %: no clear gain;
    - adding the NetVLAD similarity to the count (both standardised over the candidates,
      weights 0.25-2) only lowers the first rank (45 % or less on same).

    Attributes:
        candidates: images ``K`` of the global retrieval that are re-ranked.
        keypoints: strongest keypoints ``n`` (detector score) per image and of the query that
            take part in the score.
        min_similarity: a mutual nearest neighbour counts only above this cosine similarity,
            in ``[-1, 1)``.
        batch: images per batched product (bounds the memory to ``batch n^2`` floats).
    """

    candidates: int = 50
    keypoints: int = 512
    min_similarity: float = 0.0
    batch: int = 16

    def __post_init__(self) -> None:
        for name in ("candidates", "keypoints", "batch"):
            check_positive_int(getattr(self, name), name)
        if not -1.0 <= self.min_similarity < 1.0:
            raise ValueError(f"min_similarity must be in [-1, 1), got {self.min_similarity!r}")


def mutual_nn_counts(
    query: torch.Tensor, database: torch.Tensor, valid: torch.Tensor, min_similarity: float
) -> torch.Tensor:
    """Mutual-nearest-neighbour matches of one query against a batch of images.

    Args:
        query: (n, D) float L2-normalised query descriptors.
        database: (K, m, D) float L2-normalised descriptors of K images, padded to m.
        valid: (K, m) bool, false on padding.
        min_similarity: matches need a cosine similarity above this.

    Returns:
        (K,) int64 matches per image (0 for an image or a query without descriptors).

    Example:
        >>> q = torch.eye(3)
        >>> db = torch.stack([torch.eye(3), torch.eye(3).flip(0)])
        >>> valid = torch.tensor([[True, True, False], [True, False, False]])
        >>> mutual_nn_counts(q, db, valid, 0.5).tolist()
        [2, 1]
    """
    check_shape(query, "n,D", "query")
    check_shape(database, f"K,m,{query.shape[1]}", "database")
    check_shape(valid, f"{database.shape[0]},{database.shape[1]}", "valid")
    k, m = valid.shape
    n = query.shape[0]
    if n == 0 or m == 0:
        return torch.zeros(k, dtype=torch.int64)
    similarity = torch.matmul(database, query.T)
    if not bool(valid.all()):  # the fill is one more pass over the (K, m, n) products
        similarity.masked_fill_(~valid[:, :, None], -2.0)
    best_image, to_image = similarity.max(1)  # (K, n): each query keypoint's nearest
    to_query = similarity.argmax(2)  # (K, m): each image keypoint's nearest
    back = torch.gather(to_query, 1, to_image)  # (K, n)
    mutual = (back == torch.arange(n)[None]) & (best_image > min_similarity)
    return mutual.sum(1)


class MutualNNReranker:
    """Re-ranks database images by mutual-nearest-neighbour matches with the query.

    Args:
        descriptors: per image, (N_i, D) float L2-normalised local descriptors (N_i may be 0).
        scores: per image, (N_i,) detector scores (the ``keypoints`` strongest are kept).
        config: settings.

    Raises:
        ValueError: no images, or descriptor and score counts that differ.
        ShapeError: descriptors of different dimensions or not float.
    """

    def __init__(
        self,
        descriptors: Sequence[torch.Tensor],
        scores: Sequence[torch.Tensor],
        config: RerankConfig,
    ) -> None:
        if len(descriptors) == 0:
            raise ValueError("the re-ranker needs at least one database image, got none")
        if len(descriptors) != len(scores):
            raise ValueError(f"{len(descriptors)} descriptor sets but {len(scores)} score sets")
        dim = descriptors[0].shape[-1]
        n = config.keypoints
        self.config = config
        self.descriptors = torch.zeros(len(descriptors), n, dim)
        self.valid = torch.zeros(len(descriptors), n, dtype=torch.bool)
        for i, (d, s) in enumerate(zip(descriptors, scores, strict=True)):
            check_shape(d, f"N,{dim}", f"descriptors[{i}]")
            check_shape(s, f"{d.shape[0]}", f"scores[{i}]")
            if not d.is_floating_point():
                raise ValueError(f"descriptors[{i}] must be float (XFeat), got {d.dtype}")
            strongest = s.topk(min(n, len(s))).indices
            self.descriptors[i, : len(strongest)] = d[strongest].float()
            self.valid[i, : len(strongest)] = True

    @property
    def num_images(self) -> int:
        """Database images it ranks."""
        return int(self.valid.shape[0])

    def rerank(
        self,
        query: torch.Tensor,
        candidates: torch.Tensor,
        query_scores: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Order ``candidates`` by their matches with the query, most first.

        Args:
            query: (N, D) float L2-normalised query descriptors (N may be 0).
            candidates: (K,) int64 database images in the global retrieval's order.
            query_scores: (N,) detector scores of the query keypoints; the ``keypoints``
                strongest take part (``None``: the first ``keypoints``).

        Returns:
            ``(matches (K,), images (K,))`` int64, most matches first; ties (e.g. a query
            without keypoints) keep the order of ``candidates``.

        Raises:
            ShapeError: a query of another descriptor dimension or ``candidates`` not a vector.
            IndexError: a candidate outside the database.
        """
        check_shape(query, f"N,{self.descriptors.shape[2]}", "query")
        check_shape(candidates, "K", "candidates")
        if bool(((candidates < 0) | (candidates >= self.num_images)).any()):
            raise IndexError(f"candidates must lie in [0, {self.num_images})")
        keep = min(self.config.keypoints, len(query))
        if query_scores is None:
            query = query[:keep]
        else:
            check_shape(query_scores, f"{len(query)}", "query_scores")
            query = query[query_scores.topk(keep).indices]
        query = query.float()
        batches = candidates.long().split(self.config.batch)
        with torch.no_grad():
            matches = torch.cat(
                [
                    mutual_nn_counts(
                        query, self.descriptors[b], self.valid[b], self.config.min_similarity
                    )
                    for b in batches
                ]
            )
        order = torch.sort(matches, descending=True, stable=True).indices
        return matches[order], candidates[order]

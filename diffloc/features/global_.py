"""Global image descriptors: the NetVLAD layer (with VLAD-like k-means init) and bag of words.

NetVLAD (Arandjelovic et al., CVPR 2016) aggregates a dense descriptor map ``x_i`` (D channels
at N locations) into K residual sums ``V_k = sum_i a_k(x_i) (x_i - c_k)`` with the soft
assignment ``a_k(x) = softmax_k(w_k^T x + b_k)``. Initialising ``w_k = 2 alpha c_k`` and
``b_k = -alpha ||c_k||^2`` from k-means centroids ``c_k`` makes ``a_k(x)`` equal to
``softmax_k(-alpha ||x - c_k||^2)``, which tends to classic (hard) VLAD as alpha grows. Each
``V_k`` is L2-normalised (intra-normalisation), the concatenation is L2-normalised, and an
optional PCA whitening fitted on database descriptors projects it to fewer dimensions.

The bag-of-words baseline (Sivic and Zisserman 2003; the DBoW2 scoring of Galvez-Lopez and
Tardos 2012 with L2 instead of L1 norms) quantises local descriptors to a k-means vocabulary,
weights term frequencies by ``idf = log(N_images / N_images_with_word)`` and scores queries
against the database through an inverted index stored as CSR arrays.

Fine-tuning NetVLAD with a triplet loss lives in :mod:`diffloc.features.netvlad_training`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from diffloc.checks import check_finite, check_positive_int, check_shape

__all__ = ["BagOfWords", "NetVLAD", "kmeans", "nearest_centroids", "netvlad_from_dense_maps"]

_CHUNK_ROWS = 32768
"""Rows of descriptors per distance-matrix block (bounds memory to chunk x K floats)."""
_ASSIGNMENT_RATIO = 100.0
"""Data-driven alpha: on average the nearest centroid gets this many times the weight of the
second nearest (``alpha = log(ratio) / mean(d2_second - d2_nearest)``)."""


def _check_descriptors(x: torch.Tensor, name: str) -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    check_shape(x, "M,D", name)
    if not x.is_floating_point():
        raise TypeError(f"{name} must be floating point, got {x.dtype}")
    check_finite(x, name)
    return x


def nearest_centroids(
    x: torch.Tensor, centroids: torch.Tensor, n: int = 1, chunk_rows: int = _CHUNK_ROWS
) -> tuple[torch.Tensor, torch.Tensor]:
    """Squared Euclidean distances and indices of the ``n`` nearest centroids of each row.

    Args:
        x: (M, D) points.
        centroids: (K, D) centroids, K >= n.
        n: neighbours per point.
        chunk_rows: points per block of the (block, K) distance matrix.

    Returns:
        ``(squared_distances (M, n), indices (M, n))``, nearest first.

    Example:
        >>> d2, idx = nearest_centroids(torch.tensor([[0.9, 0.0]]), torch.eye(2))
        >>> idx.tolist()
        [[0]]
    """
    check_shape(x, "M,D", "x")
    check_shape(centroids, f"K,{x.shape[1]}", "centroids")
    if not 1 <= n <= centroids.shape[0]:
        raise ValueError(f"n must be in [1, {centroids.shape[0]}], got {n}")
    c_sq = (centroids * centroids).sum(1)
    values, indices = [], []
    for block in x.split(chunk_rows):
        d2 = (block * block).sum(1, keepdim=True) - 2.0 * block @ centroids.T + c_sq
        v, i = torch.topk(d2.clamp_min(0.0), n, dim=1, largest=False)
        values.append(v)
        indices.append(i)
    return torch.cat(values), torch.cat(indices)


def _kmeans_plus_plus(x: torch.Tensor, k: int, generator: torch.Generator) -> torch.Tensor:
    """k-means++ seeding: each new centroid is a point drawn with probability ~ D(x)^2."""
    x_sq = (x * x).sum(1)

    def squared_distances_to(index: int) -> torch.Tensor:
        return (x_sq - 2.0 * (x @ x[index]) + x_sq[index]).clamp_min(0.0)

    chosen = [int(torch.randint(len(x), (1,), generator=generator))]
    d2 = squared_distances_to(chosen[0])
    for _ in range(1, k):
        weights = d2.double() if bool(d2.sum() > 0) else torch.ones(len(x), dtype=torch.float64)
        chosen.append(int(torch.multinomial(weights, 1, generator=generator)))
        d2 = torch.minimum(d2, squared_distances_to(chosen[-1]))
    return x[chosen].clone()


def kmeans(
    x: torch.Tensor,
    k: int,
    generator: torch.Generator,
    num_iters: int = 50,
    chunk_rows: int = _CHUNK_ROWS,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Lloyd's k-means with k-means++ seeding (vectorised, deterministic given ``generator``).

    A cluster that becomes empty is re-seeded at the point farthest from its centroid.

    Args:
        x: (M, D) floating point points, M >= k.
        k: number of clusters.
        generator: CPU generator for the seeding.
        num_iters: maximum Lloyd iterations (stops early when no label changes).
        chunk_rows: points per distance-matrix block.

    Returns:
        ``(centroids (k, D), labels (M,))`` in ``x``'s dtype; ``labels`` are the nearest
        centroids of the returned ``centroids``.

    Raises:
        ShapeError: ``x`` is not (M, D).
        ValueError: M < k, non-finite values, non-positive ``k`` or ``num_iters``.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> x = torch.cat([torch.zeros(5, 2), torch.ones(5, 2)])
        >>> centroids, labels = kmeans(x, 2, g)
        >>> sorted(centroids.sum(1).tolist())
        [0.0, 2.0]
    """
    x = _check_descriptors(x, "x")
    k = check_positive_int(k, "k")
    check_positive_int(num_iters, "num_iters")
    if len(x) < k:
        raise ValueError(f"k-means needs at least k={k} points, got {len(x)}")
    centroids = _kmeans_plus_plus(x, k, generator)
    labels = nearest_centroids(x, centroids, 1, chunk_rows)[1][:, 0]
    for _ in range(num_iters):
        counts = torch.bincount(labels, minlength=k)
        sums = torch.zeros_like(centroids).index_add_(0, labels, x)
        centroids = sums / counts.clamp_min(1).unsqueeze(1).to(x.dtype)
        empty = torch.nonzero(counts == 0).flatten()
        if len(empty):
            d2 = ((x - centroids[labels]) ** 2).sum(1)
            centroids[empty] = x[torch.topk(d2, len(empty)).indices]
        new_labels = nearest_centroids(x, centroids, 1, chunk_rows)[1][:, 0]
        if torch.equal(new_labels, labels):
            break
        labels = new_labels
    return centroids, labels


def _data_alpha(x: torch.Tensor, centroids: torch.Tensor) -> float:
    """Alpha giving the nearest centroid on average 100x the weight of the second nearest."""
    if len(centroids) < 2:
        return 1.0
    d2 = nearest_centroids(x, centroids, 2)[0]
    gap = float((d2[:, 1] - d2[:, 0]).mean())
    return math.log(_ASSIGNMENT_RATIO) / max(gap, 1e-12)


class NetVLAD(nn.Module):
    """NetVLAD pooling of a dense descriptor map into one global descriptor.

    Input descriptors are L2-normalised per location first. Parameters start at zero (uniform
    assignment); call :meth:`init_from_kmeans` (or load a state dict) before use.

    Args:
        num_clusters: K.
        dim: D, the channels of the dense descriptor map.
        whiten_dim: output dimension of the PCA whitening, or ``None`` for no whitening
            (output ``K * D``). The whitening buffers are filled by :meth:`fit_whitening`.

    Example:
        >>> vlad = NetVLAD(num_clusters=8, dim=64)
        >>> sizes = vlad.init_from_kmeans(torch.randn(1000, 64), torch.Generator().manual_seed(0))
        >>> vlad(torch.randn(2, 64, 15, 20)).shape
        torch.Size([2, 512])
    """

    def __init__(self, num_clusters: int = 64, dim: int = 64, whiten_dim: int | None = None):
        super().__init__()
        self.num_clusters = check_positive_int(num_clusters, "num_clusters")
        self.dim = check_positive_int(dim, "dim")
        if whiten_dim is not None:
            whiten_dim = check_positive_int(whiten_dim, "whiten_dim")
        self.whiten_dim = whiten_dim
        self.centroids = nn.Parameter(torch.zeros(num_clusters, dim))
        self.assignment = nn.Conv2d(dim, num_clusters, kernel_size=1, bias=True)
        nn.init.zeros_(self.assignment.weight)
        nn.init.zeros_(self.assignment.bias)
        self.register_buffer("alpha", torch.zeros((), dtype=torch.float64))
        if whiten_dim is not None:
            self.register_buffer("pca_mean", torch.zeros(num_clusters * dim))
            self.register_buffer("pca_projection", torch.zeros(num_clusters * dim, whiten_dim))
            self.register_buffer("whitening_fitted", torch.tensor(False))

    @property
    def output_dim(self) -> int:
        """Length of :meth:`forward`'s descriptors: ``whiten_dim`` or ``K * D``."""
        return self.num_clusters * self.dim if self.whiten_dim is None else self.whiten_dim

    @torch.no_grad()
    def init_from_kmeans(
        self,
        descriptors: torch.Tensor,
        generator: torch.Generator,
        alpha: float | None = None,
        num_iters: int = 50,
    ) -> torch.Tensor:
        """Set centroids by k-means and the assignment so that it is a VLAD soft assignment.

        ``w_k = 2 alpha c_k``, ``b_k = -alpha ||c_k||^2``, so
        ``softmax_k(w_k^T x + b_k) = softmax_k(-alpha ||x - c_k||^2)``.

        Args:
            descriptors: (M, D) local descriptors sampled from database images (normalised
                here, as in :meth:`forward`), M >= K.
            generator: CPU generator for the k-means seeding.
            alpha: assignment sharpness; ``None`` picks it from the data so that the nearest
                centroid gets on average 100x the weight of the second nearest.
            num_iters: maximum k-means iterations.

        Returns:
            (K,) int64 cluster sizes.
        """
        descriptors = _check_descriptors(descriptors, "descriptors")
        check_shape(descriptors, f"M,{self.dim}", "descriptors")
        x = F.normalize(descriptors.detach().float().cpu(), dim=1)
        centroids, labels = kmeans(x, self.num_clusters, generator, num_iters)
        if alpha is None:
            alpha = _data_alpha(x, centroids)
        if not (math.isfinite(alpha) and alpha > 0):
            raise ValueError(f"alpha must be positive and finite, got {alpha}")
        device = self.centroids.device
        centroids = centroids.to(device)
        self.alpha.fill_(alpha)
        self.centroids.copy_(centroids)
        self.assignment.weight.copy_((2.0 * alpha * centroids)[:, :, None, None])
        self.assignment.bias.copy_(-alpha * (centroids * centroids).sum(1))
        return torch.bincount(labels, minlength=self.num_clusters)

    def aggregate(self, x: torch.Tensor) -> torch.Tensor:
        """NetVLAD descriptors without whitening.

        Args:
            x: (B, D, h, w) dense descriptors.

        Returns:
            (B, K * D) unit-norm descriptors (cluster-major: entries ``k*D:(k+1)*D`` are the
            intra-normalised residual sum of cluster k).
        """
        check_shape(x, f"B,{self.dim},h,w", "x")
        x = F.normalize(x, dim=1)
        assignment = F.softmax(self.assignment(x).flatten(2), dim=1)  # (B, K, N)
        local = x.flatten(2)  # (B, D, N)
        vlad = assignment @ local.transpose(1, 2)  # (B, K, D)
        vlad = vlad - assignment.sum(2, keepdim=True) * self.centroids
        vlad = F.normalize(vlad, dim=2)
        return F.normalize(vlad.flatten(1), dim=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Global descriptors of dense descriptor maps.

        Args:
            x: (B, D, h, w) dense descriptors (e.g. :class:`~diffloc.features.dense.DenseXFeat`).

        Returns:
            (B, output_dim) unit-norm descriptors.

        Raises:
            ShapeError: ``x`` is not (B, D, h, w) with this layer's D.
            RuntimeError: whitening was requested but :meth:`fit_whitening` was not called.
        """
        vlad = self.aggregate(x)
        if self.whiten_dim is None:
            return vlad
        if not bool(self.whitening_fitted):
            raise RuntimeError("NetVLAD whitening is not fitted; call fit_whitening first")
        return F.normalize((vlad - self.pca_mean) @ self.pca_projection, dim=1)

    @torch.no_grad()
    def fit_whitening(self, vlad: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
        """Fit the PCA whitening on database descriptors (SVD of the centred descriptors).

        The projection maps a centred descriptor onto the top ``whiten_dim`` principal axes,
        each divided by ``sqrt(variance + eps)``.

        Args:
            vlad: (M, K * D) descriptors from :meth:`aggregate`, M > whiten_dim.
            eps: regulariser added to the variances.

        Returns:
            (whiten_dim,) variances of the kept principal axes, largest first.

        Raises:
            RuntimeError: the layer was built without ``whiten_dim``.
            ValueError: too few descriptors for ``whiten_dim`` components.
        """
        if self.whiten_dim is None:
            raise RuntimeError("this NetVLAD has no whitening (whiten_dim=None)")
        vlad = _check_descriptors(vlad, "vlad")
        check_shape(vlad, f"M,{self.num_clusters * self.dim}", "vlad")
        if len(vlad) <= self.whiten_dim:
            raise ValueError(
                f"whitening to {self.whiten_dim} dimensions needs more than {self.whiten_dim} "
                f"descriptors, got {len(vlad)}"
            )
        x = vlad.detach().double()
        mean = x.mean(0)
        _, singular, vh = torch.linalg.svd(x - mean, full_matrices=False)
        variance = singular[: self.whiten_dim] ** 2 / (len(x) - 1)
        projection = vh[: self.whiten_dim].T / torch.sqrt(variance + eps)
        self.pca_mean.copy_(mean)
        self.pca_projection.copy_(projection)
        self.whitening_fitted.fill_(True)
        return variance

    @torch.no_grad()
    def whitened(self, mean: torch.Tensor, projection: torch.Tensor) -> NetVLAD:
        """A copy of this layer (clusters, assignment) that whitens with a given projection.

        Args:
            mean: (K * D,) mean subtracted from :meth:`aggregate`'s descriptors.
            projection: (K * D, W) projection (e.g.
                :func:`~diffloc.features.learned_whitening.learned_whitening`); the copy's
                descriptors are ``normalise((aggregate(x) - mean) @ projection)``, W floats.

        Raises:
            ShapeError: ``mean`` or ``projection`` of the wrong size.

        Example:
            >>> vlad = NetVLAD(num_clusters=2, dim=4)
            >>> white = vlad.whitened(torch.zeros(8), torch.eye(8)[:, :3])
            >>> white.output_dim, white(torch.randn(1, 4, 2, 2)).shape
            (3, torch.Size([1, 3]))
        """
        check_shape(mean, f"{self.num_clusters * self.dim}", "mean")
        check_shape(projection, f"{self.num_clusters * self.dim},W", "projection")
        layer = NetVLAD(self.num_clusters, self.dim, whiten_dim=projection.shape[1])
        state = {
            k: v for k, v in self.state_dict().items() if not k.startswith(("pca_", "whitening"))
        }
        layer.load_state_dict(
            {
                **state,
                "pca_mean": mean.float(),
                "pca_projection": projection.float(),
                "whitening_fitted": torch.tensor(True),
            }
        )
        return layer.to(self.centroids.device).eval()


def netvlad_from_dense_maps(
    maps: torch.Tensor,
    num_clusters: int,
    samples_per_image: int,
    generator: torch.Generator,
    num_iters: int = 30,
) -> NetVLAD:
    """A NetVLAD layer initialised by k-means on descriptors sampled from dense maps.

    ``samples_per_image`` locations are drawn uniformly (with replacement) from every map and
    the layer is set by :meth:`NetVLAD.init_from_kmeans` on them: VLAD-like, no training.

    Args:
        maps: (M, D, h, w) dense descriptor maps of the database images (any float dtype).
        num_clusters: K.
        samples_per_image: locations drawn per map.
        generator: CPU generator of the sampling and the k-means seeding.
        num_iters: most k-means iterations.

    Returns:
        The initialised :class:`NetVLAD` (no whitening).

    Raises:
        ShapeError: ``maps`` not (M, D, h, w).
        ValueError: no maps, or fewer samples than clusters.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> netvlad_from_dense_maps(torch.randn(4, 64, 6, 8), 8, 50, g).output_dim
        512
    """
    check_shape(maps, "M,D,h,w", "maps")
    if maps.shape[0] == 0:
        raise ValueError("netvlad_from_dense_maps needs at least one map")
    check_positive_int(samples_per_image, "samples_per_image")
    flat = maps.flatten(2)
    picks = torch.randint(flat.shape[2], (len(maps), samples_per_image), generator=generator)
    samples = torch.gather(flat, 2, picks[:, None].expand(-1, flat.shape[1], -1).to(flat.device))
    samples = samples.transpose(1, 2).reshape(-1, flat.shape[1]).float()
    if len(samples) < num_clusters:
        raise ValueError(
            f"{len(samples)} sampled descriptors cannot seed {num_clusters} NetVLAD clusters"
        )
    netvlad = NetVLAD(num_clusters, flat.shape[1])
    netvlad.init_from_kmeans(samples, generator, num_iters=num_iters)
    return netvlad


class BagOfWords:
    """Bag-of-visual-words image retrieval with tf-idf weights and an inverted index.

    Args:
        vocabulary: (W, D) float visual words (k-means centroids of local descriptors).

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> bow = BagOfWords.train(torch.randn(2000, 64), num_words=32, generator=g)
        >>> database = [torch.randn(100, 64) for _ in range(5)]
        >>> bow.build(database)
        >>> scores, indices = bow.search([database[3]], k=2)
        >>> int(indices[0, 0])
        3
    """

    def __init__(self, vocabulary: torch.Tensor) -> None:
        self.vocabulary = _check_descriptors(vocabulary, "vocabulary").detach().float().cpu()
        self.idf: torch.Tensor | None = None
        self.indptr = torch.zeros(self.num_words + 1, dtype=torch.int64)
        self.doc_ids = torch.zeros(0, dtype=torch.int64)
        self.weights = torch.zeros(0)
        self.num_images = 0

    @classmethod
    def train(
        cls,
        descriptors: torch.Tensor,
        num_words: int,
        generator: torch.Generator,
        num_iters: int = 25,
    ) -> BagOfWords:
        """Learn a flat vocabulary by k-means on local descriptors.

        Args:
            descriptors: (M, D) float local descriptors, M >= num_words.
            num_words: W.
            generator: CPU generator for the k-means seeding.
            num_iters: maximum k-means iterations.

        Returns:
            An unbuilt :class:`BagOfWords` (call :meth:`build` with database images).
        """
        descriptors = _check_descriptors(descriptors, "descriptors").detach().float().cpu()
        return cls(kmeans(descriptors, num_words, generator, num_iters)[0])

    @property
    def num_words(self) -> int:
        return self.vocabulary.shape[0]

    def words(self, descriptors: torch.Tensor) -> torch.Tensor:
        """(N,) int64 nearest word of each (N, D) descriptor."""
        descriptors = _check_descriptors(descriptors, "descriptors")
        check_shape(descriptors, f"N,{self.vocabulary.shape[1]}", "descriptors")
        return nearest_centroids(descriptors.detach().float().cpu(), self.vocabulary)[1][:, 0]

    def _term_frequencies(
        self, descriptor_sets: Sequence[torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Sparse ``(rows, words, tf)`` with ``tf = count / descriptors_in_image``."""
        if isinstance(descriptor_sets, torch.Tensor) or not len(descriptor_sets):
            raise TypeError("descriptor_sets must be a non-empty sequence of (N_i, D) tensors")
        sizes = torch.tensor([len(d) for d in descriptor_sets], dtype=torch.int64)
        for i, d in enumerate(descriptor_sets):
            check_shape(d, f"N,{self.vocabulary.shape[1]}", f"descriptor_sets[{i}]")
        words = self.words(torch.cat([d.detach().float().cpu() for d in descriptor_sets]))
        image = torch.repeat_interleave(torch.arange(len(sizes)), sizes)
        keys, counts = torch.unique(image * self.num_words + words, return_counts=True)
        rows = keys // self.num_words
        return rows, keys % self.num_words, counts.float() / sizes[rows].float()

    def _normalised_tfidf(
        self, rows: torch.Tensor, words: torch.Tensor, tf: torch.Tensor, num_rows: int
    ) -> torch.Tensor:
        """Values of the sparse tf-idf vectors, each row scaled to unit L2 norm."""
        values = tf * self.idf[words]
        norm = torch.zeros(num_rows).index_add_(0, rows, values * values).sqrt()[rows]
        return torch.where(norm > 0, values / norm.clamp_min(1e-30), 0.0)

    def _tfidf(
        self, descriptor_sets: Sequence[torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Sparse L2-normalised tf-idf vectors ``(rows, words, values)``."""
        if self.idf is None:
            raise RuntimeError("BagOfWords has no database yet; call build first")
        rows, words, tf = self._term_frequencies(descriptor_sets)
        return rows, words, self._normalised_tfidf(rows, words, tf, len(descriptor_sets))

    def build(self, descriptor_sets: Sequence[torch.Tensor]) -> None:
        """Set the idf weights from database images and build the inverted index.

        Args:
            descriptor_sets: N_db tensors (N_i, D), the local descriptors of each image.
        """
        num_images = len(descriptor_sets)
        rows, words, tf = self._term_frequencies(descriptor_sets)
        df = torch.bincount(words, minlength=self.num_words).float()  # (row, word) are unique
        self.idf = torch.where(df > 0, torch.log(num_images / df.clamp_min(1.0)), 0.0)
        values = self._normalised_tfidf(rows, words, tf, num_images)
        order = torch.argsort(words * num_images + rows)
        counts = torch.bincount(words, minlength=self.num_words)
        self.indptr = torch.cat([torch.zeros(1, dtype=torch.int64), counts.cumsum(0)])
        self.doc_ids = rows[order]
        self.weights = values[order]
        self.num_images = num_images

    def state_arrays(self) -> dict[str, torch.Tensor]:
        """The vocabulary and the built index as named tensors (for ``.npz`` files)."""
        if self.idf is None:
            raise RuntimeError("BagOfWords has no database yet; call build first")
        return {
            "vocabulary": self.vocabulary,
            "idf": self.idf,
            "indptr": self.indptr,
            "doc_ids": self.doc_ids,
            "weights": self.weights,
            "num_images": torch.tensor(self.num_images),
        }

    @classmethod
    def from_state_arrays(cls, arrays: dict[str, torch.Tensor]) -> BagOfWords:
        """Rebuild a built :class:`BagOfWords` from :meth:`state_arrays`.

        Raises:
            ValueError: a missing array or inconsistent sizes.
        """
        names = ("vocabulary", "idf", "indptr", "doc_ids", "weights", "num_images")
        missing = [n for n in names if n not in arrays]
        if missing:
            raise ValueError(f"bag-of-words state lacks {missing}")
        bow = cls(arrays["vocabulary"])
        if arrays["idf"].shape != (bow.num_words,) or arrays["indptr"].shape != (
            bow.num_words + 1,
        ):
            raise ValueError("bag-of-words state: idf/indptr sizes do not match the vocabulary")
        bow.idf = arrays["idf"].float()
        bow.indptr = arrays["indptr"].long()
        bow.doc_ids = arrays["doc_ids"].long()
        bow.weights = arrays["weights"].float()
        bow.num_images = int(arrays["num_images"])
        return bow

    def histograms(self, descriptor_sets: Sequence[torch.Tensor]) -> torch.Tensor:
        """Dense (B, W) L2-normalised tf-idf histograms (a reference for :meth:`score`)."""
        rows, words, values = self._tfidf(descriptor_sets)
        dense = torch.zeros(len(descriptor_sets), self.num_words)
        dense[rows, words] = values
        return dense

    def score(self, descriptor_sets: Sequence[torch.Tensor]) -> torch.Tensor:
        """Cosine similarities of query images to every database image via the inverted index.

        Args:
            descriptor_sets: Q tensors (N_i, D) of query local descriptors.

        Returns:
            (Q, N_db) scores in [0, 1].
        """
        rows, words, values = self._tfidf(descriptor_sets)
        starts = self.indptr[words]
        lengths = self.indptr[words + 1] - starts
        entry = torch.repeat_interleave(torch.arange(len(words)), lengths)
        first = torch.repeat_interleave(lengths.cumsum(0) - lengths, lengths)
        posting = starts[entry] + torch.arange(len(entry)) - first
        flat = rows[entry] * self.num_images + self.doc_ids[posting]
        scores = torch.zeros(len(descriptor_sets) * self.num_images)
        scores.index_add_(0, flat, values[entry] * self.weights[posting])
        return scores.view(len(descriptor_sets), self.num_images)

    def search(
        self, descriptor_sets: Sequence[torch.Tensor], k: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Top-k database images of each query: ``(scores (Q, k'), indices (Q, k'))``.

        ``k' = min(k, N_db)``; scores descend.
        """
        k = check_positive_int(k, "k")
        scores = self.score(descriptor_sets)
        return torch.topk(scores, min(k, self.num_images), dim=1)

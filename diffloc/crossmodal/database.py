"""RGB-D image databases for localisation (seed 2 Sec. III-D/E): rendered or real.

A :class:`RenderedDatabase` holds M posed RGB-D images with what Algorithm 1 needs at query
time: XFeat local features per image and a NetVLAD global descriptor per image (the NetVLAD
layer itself is kept too, initialised VLAD-like by k-means on the images' dense XFeat maps,
:func:`~diffloc.features.global_.netvlad_from_dense_maps`). The images may be renders of any
:class:`~diffloc.crossmodal.synthesize.RGBDMap` (:func:`render_database`) or real posed
RGB-D frames (:func:`build_database`); the localiser does not tell them apart.

Holes are pixels with depth 0; :attr:`RenderedDatabase.holes` is their share per image.

Files: a folder with ``database.npz`` (arrays, ``allow_pickle=False``; rgb as uint8) and
``database.json`` (``format_version``, camera, counts, source), written together atomically.
Loading validates values: finite poses with a rigid last row, depth finite and >= 0, and counts
that agree (images, depths, poses, features, descriptors).

Usage (extracts XFeat features of every render; ``tests/test_rendered_database.py`` runs it on
the tiny scene)::

    db = render_database(cloud, selection.T_wc, camera, DatabaseConfig(), "tls single")
    db.save("out/tls_single")
    same = RenderedDatabase.load("out/tls_single")
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from diffloc.checks import check_positive_int, check_shape
from diffloc.crossmodal.synthesize import RGBD, RGBDMap, hole_fraction, render_views
from diffloc.features.global_ import NetVLAD, netvlad_from_dense_maps
from diffloc.features.local import Features, XFeatConfig, XFeatExtractor
from diffloc.geometry.camera import PinholeCamera
from diffloc.io.atomic import atomic_directory, atomic_open, atomic_write_text
from diffloc.io.json_record import read_json_record
from diffloc.io.npz import read_npz_archive
from diffloc.progress import progress

__all__ = [
    "DATABASE_FORMAT_VERSION",
    "DatabaseConfig",
    "RenderedDatabase",
    "build_database",
    "render_database",
]

DATABASE_FORMAT_VERSION = 1
_KIND = "diffloc-rgbd-database"
_NPZ, _JSON = "database.npz", "database.json"
_FEATURE_ARRAYS = ("keypoints", "scores", "descriptors", "sizes")


@dataclass(frozen=True)
class DatabaseConfig:
    """Settings of :func:`build_database`.

    Attributes:
        max_keypoints: XFeat keypoints per image (seed 2 / XFeat: 1024).
        netvlad_clusters: NetVLAD clusters K (global descriptors of 64 K floats).
        samples_per_image: dense descriptors per image for the NetVLAD k-means.
        kmeans_iterations: most k-means iterations.
        batch_size: images per render call and per XFeat pass.
        seed: seed of the k-means sampling and seeding.
    """

    max_keypoints: int = 1024
    netvlad_clusters: int = 32
    samples_per_image: int = 200
    kmeans_iterations: int = 30
    batch_size: int = 8
    seed: int = 0

    def __post_init__(self) -> None:
        for name in (
            "max_keypoints",
            "netvlad_clusters",
            "samples_per_image",
            "kmeans_iterations",
            "batch_size",
        ):
            check_positive_int(getattr(self, name), name)


@dataclass(frozen=True, eq=False)
class RenderedDatabase:
    """M posed RGB-D images with local features and global descriptors.

    Attributes:
        T_wc: (M, 4, 4) float64 camera-to-world poses.
        rgb: (M, 3, H, W) float32 colours in [0, 1].
        depth: (M, 1, H, W) float32 z-depth in metres, 0 = hole.
        camera: the (unbatched) camera of every image, size W x H.
        features: M XFeat :class:`Features` (keypoints in the image's pixels).
        global_descriptors: (M, G) float32 NetVLAD descriptors, G = ``netvlad.output_dim``.
        netvlad: the NetVLAD layer that made them (queries are described with it).
        source: what the images are (e.g. ``"tls_map single-pass Eq. 2"``).
        real: (M,) bool, which images are real photographs rather than renders (``None``:
            none; a file without the array reads as renders).

    Raises:
        ValueError: an empty database, NaN/inf or non-rigid poses, negative or NaN depth,
            colours outside [0, 1], counts or sizes that disagree (ShapeError is a ValueError).
    """

    T_wc: torch.Tensor
    rgb: torch.Tensor
    depth: torch.Tensor
    camera: PinholeCamera
    features: tuple[Features, ...]
    global_descriptors: torch.Tensor
    netvlad: NetVLAD
    source: str = ""
    real: torch.Tensor | None = None

    def __post_init__(self) -> None:
        check_shape(self.T_wc, "M,4,4", "T_wc")
        m = self.T_wc.shape[0]
        if m == 0:
            raise ValueError("the database is empty: it has no images")
        _check_poses(self.T_wc)
        if not isinstance(self.camera, PinholeCamera) or self.camera.batch_shape != ():
            raise ValueError("camera must be one (unbatched) PinholeCamera")
        h, w = self.camera.height, self.camera.width
        check_shape(self.rgb, f"{m},3,{h},{w}", "rgb")
        check_shape(self.depth, f"{m},1,{h},{w}", "depth")
        if not bool(torch.isfinite(self.depth).all() and (self.depth >= 0).all()):
            raise ValueError("depth must be finite and >= 0 (0 = no depth)")
        if not bool(((self.rgb >= 0) & (self.rgb <= 1)).all()):
            raise ValueError("rgb must lie in [0, 1]")
        if len(self.features) != m:
            raise ValueError(f"{m} images but {len(self.features)} feature sets")
        check_shape(self.global_descriptors, f"{m},{self.netvlad.output_dim}", "global_descriptors")
        if not bool(torch.isfinite(self.global_descriptors).all()):
            raise ValueError("global_descriptors contains NaN or inf")
        real = torch.zeros(m, dtype=torch.bool) if self.real is None else self.real
        check_shape(real, f"{m}", "real")
        if real.dtype != torch.bool:
            raise ValueError(f"real must be a bool tensor, got {real.dtype}")
        object.__setattr__(self, "real", real)
        object.__setattr__(self, "T_wc", self.T_wc.to(torch.float64))
        object.__setattr__(self, "features", tuple(self.features))

    @property
    def num_images(self) -> int:
        return int(self.T_wc.shape[0])

    @property
    def holes(self) -> torch.Tensor:
        """(M,) float32 share of pixels without depth in each image."""
        return hole_fraction(self.depth)

    def save(self, path: str | os.PathLike, overwrite: bool = False) -> Path:
        """Write the folder ``path`` (``database.npz`` + ``database.json``) atomically.

        Args:
            path: the folder to create.
            overwrite: replace an existing folder.

        Returns:
            ``path`` as a :class:`~pathlib.Path`.

        Raises:
            FileExistsError: ``path`` exists and ``overwrite`` is false.
        """
        path = Path(path)
        counts = torch.tensor([len(f) for f in self.features], dtype=torch.int64)
        arrays = {
            "T_wc": self.T_wc,
            "rgb": (self.rgb * 255.0).round().to(torch.uint8),
            "depth": self.depth,
            "feature_counts": counts,
            "global_descriptors": self.global_descriptors,
            "real": self.real,
            **{
                name: torch.cat([getattr(f, name) for f in self.features])
                for name in _FEATURE_ARRAYS
            },
            **{f"netvlad.{k}": v for k, v in self.netvlad.state_dict().items()},
        }
        meta = {
            "format_version": DATABASE_FORMAT_VERSION,
            "kind": _KIND,
            "source": self.source,
            "num_images": self.num_images,
            "num_keypoints": int(counts.sum()),
            "camera": _camera_to_json(self.camera),
            "netvlad": {"num_clusters": self.netvlad.num_clusters, "dim": self.netvlad.dim},
            "mean_hole_fraction": float(self.holes.mean()),
        }
        with atomic_directory(path, overwrite=overwrite) as tmp:
            with atomic_open(tmp / _NPZ, "wb") as handle:
                np.savez(handle, **{k: v.detach().cpu().numpy() for k, v in arrays.items()})
            atomic_write_text(tmp / _JSON, json.dumps(meta, indent=2) + "\n")
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> RenderedDatabase:
        """Read a folder written by :meth:`save` and validate it.

        Raises:
            FileNotFoundError: a missing file (named).
            ValueError: a foreign, corrupt or inconsistent database; the message names the file.
        """
        path = Path(path)
        meta_path, npz_path = path / _JSON, path / _NPZ
        for p in (meta_path, npz_path):
            if not p.is_file():
                raise FileNotFoundError(f"{p} is missing: not a saved RGB-D database folder")
        meta = read_json_record(meta_path)
        if meta.get("kind") != _KIND:
            raise ValueError(f"{meta_path}: not a diffloc RGB-D database (kind {_KIND!r})")
        if meta.get("format_version") != DATABASE_FORMAT_VERSION:
            raise ValueError(
                f"{meta_path}: format_version {meta.get('format_version')!r}, this diffloc "
                f"reads {DATABASE_FORMAT_VERSION}; rebuild the database"
            )
        arrays = {k: torch.from_numpy(v) for k, v in read_npz_archive(npz_path).items()}
        try:
            return _from_arrays(meta, arrays)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{npz_path}: invalid RGB-D database ({exc})") from exc


def _check_poses(T_wc: torch.Tensor) -> None:
    if not bool(torch.isfinite(T_wc).all()):
        raise ValueError("T_wc contains NaN or inf poses")
    last = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T_wc.dtype)
    if not bool((T_wc[:, 3] == last).all()):
        raise ValueError("T_wc rows must end in [0, 0, 0, 1]")


def _camera_to_json(camera: PinholeCamera) -> dict:
    distortion = None if camera.distortion is None else camera.distortion.tolist()
    return {
        "width": camera.width,
        "height": camera.height,
        **{k: float(getattr(camera, k)) for k in ("fx", "fy", "cx", "cy")},
        "distortion": distortion,
    }


def _from_arrays(meta: dict, arrays: dict[str, torch.Tensor]) -> RenderedDatabase:
    camera = PinholeCamera(**meta["camera"])
    counts = arrays["feature_counts"]
    if counts.ndim != 1 or bool((counts < 0).any()):
        raise ValueError("feature_counts must be a vector of counts >= 0")
    if meta.get("num_images") != len(arrays["T_wc"]):
        raise ValueError(
            f"JSON says {meta.get('num_images')} images, arrays hold {len(arrays['T_wc'])}"
        )
    total = int(counts.sum())
    for name in _FEATURE_ARRAYS:
        if len(arrays[name]) != total:
            raise ValueError(f"{name} has {len(arrays[name])} rows, feature_counts sum to {total}")
    parts = {name: arrays[name].split(counts.tolist()) for name in _FEATURE_ARRAYS}
    features = tuple(
        Features(*(parts[name][i] for name in _FEATURE_ARRAYS)) for i in range(len(counts))
    )
    state = {k.removeprefix("netvlad."): v for k, v in arrays.items() if k.startswith("netvlad.")}
    netvlad = NetVLAD(meta["netvlad"]["num_clusters"], meta["netvlad"]["dim"])
    netvlad.load_state_dict(state)
    return RenderedDatabase(
        T_wc=arrays["T_wc"],
        rgb=arrays["rgb"].float() / 255.0,
        depth=arrays["depth"],
        camera=camera,
        features=features,
        global_descriptors=arrays["global_descriptors"],
        netvlad=netvlad.eval(),
        source=str(meta.get("source", "")),
        real=arrays["real"].to(torch.bool) if "real" in arrays else None,
    )


@torch.no_grad()
def build_database(
    views: RGBD,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    config: DatabaseConfig,
    source: str = "",
    extractor: XFeatExtractor | None = None,
    show_progress: bool = False,
    real: torch.Tensor | bool = False,
) -> RenderedDatabase:
    """Local features and NetVLAD descriptors of posed RGB-D images (rendered or real).

    Args:
        views: M images, rgb (M, 3, H, W) and depth (M, 1, H, W).
        T_wc: (M, 4, 4) camera-to-world poses of the images.
        camera: their (unbatched) camera, size W x H.
        config: settings.
        source: what the images are, kept in the database.
        extractor: XFeat extractor to reuse (one is made from ``config`` when ``None``);
            its ``max_keypoints`` is used as it is.
        show_progress: progress bar over the feature batches.
        real: which images are real photographs: one flag for all, or (M,) bool.

    Returns:
        The :class:`RenderedDatabase`.

    Raises:
        ValueError: an empty batch, counts or sizes that disagree, NaN poses.
    """
    if len(views) == 0:
        raise ValueError("the database is empty: no images to build it from")
    check_shape(T_wc, f"{len(views)},4,4", "T_wc")
    _check_poses(T_wc)
    if extractor is None:
        extractor = XFeatExtractor(XFeatConfig(max_keypoints=config.max_keypoints))
    features, dense = [], []
    for rgb in progress(views.rgb.split(config.batch_size), "features", show_progress):
        for f in extractor.extract(rgb):
            dense.append(f.dense.to(torch.float16))
            features.append(Features(f.keypoints, f.scores, f.descriptors, f.sizes))
    maps = torch.stack(dense)
    generator = torch.Generator().manual_seed(config.seed)
    netvlad = netvlad_from_dense_maps(
        maps, config.netvlad_clusters, config.samples_per_image, generator, config.kmeans_iterations
    ).eval()
    descriptors = torch.cat([netvlad(m.float()) for m in maps.split(config.batch_size)])
    return RenderedDatabase(
        T_wc=T_wc.to(torch.float64),
        rgb=views.rgb,
        depth=views.depth,
        camera=camera,
        features=tuple(features),
        global_descriptors=descriptors,
        netvlad=netvlad,
        source=source,
        real=torch.full((len(views),), real) if isinstance(real, bool) else real,
    )


def render_database(
    rgbd_map: RGBDMap,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    config: DatabaseConfig,
    source: str = "",
    extractor: XFeatExtractor | None = None,
    show_progress: bool = False,
) -> RenderedDatabase:
    """Render ``rgbd_map`` at the poses ``T_wc`` (M, 4, 4) and build the database of the renders.

    The poses usually come from
    :func:`~diffloc.crossmodal.pose_selection.select_render_poses`. See :func:`build_database`
    for the arguments.
    """
    views = render_views(rgbd_map, T_wc, camera, config.batch_size, show_progress)
    return build_database(views, T_wc, camera, config, source, extractor, show_progress)

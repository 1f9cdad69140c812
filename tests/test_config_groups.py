"""Every option of every config group composes with each scene into typed objects.

The options come from the filesystem (``diffloc/conf/<group>/<option>.yaml``), so a new task,
map, feature extractor or experiment is covered the moment its YAML exists.
"""

from __future__ import annotations

import itertools

import pytest
import torch
from omegaconf import OmegaConf

from diffloc.config import CONF_DIR, UnknownKeyError, compose_config, nerf_settings, to_object
from diffloc.features.local import OrbConfig, XFeatConfig
from diffloc.maps.nerf.submaps import cluster_trajectory
from diffloc.reloc.retrieval import BowConfig, NetVLADConfig

SCENES = sorted(p.stem for p in (CONF_DIR / "scene").glob("*.yaml"))


def _defaults_groups() -> set[str]:
    """The groups the primary config's defaults list names (they take ``group=option``; the
    others, such as ``experiment``, are added with ``+group=option``)."""
    groups = set()
    for entry in OmegaConf.load(CONF_DIR / "config.yaml").defaults:
        if isinstance(entry, str):
            continue
        key = next(iter(entry)).split("@")[0]
        groups.add(key.removeprefix("optional ").strip())
    return groups


def _options() -> list[tuple[str, str]]:
    """``(group, option)`` of every YAML below ``diffloc/conf`` except the primary config."""
    found = [
        (path.parent.relative_to(CONF_DIR).as_posix(), path.stem)
        for path in sorted(CONF_DIR.glob("**/*.yaml"))
        if path.parent != CONF_DIR
    ]
    assert len(found) > 20 and ("task", "calibrate_rig") in found
    return found


DEFAULTS = _defaults_groups()
CASES = [
    (group, option, scene)
    for group, option in _options()
    for scene in SCENES
    if group != "scene" or option == scene
]


def _overrides(group: str, option: str) -> list[str]:
    """The overrides that select ``option``; a scene-kind option ``<parent>/scene`` named
    ``<choice>_<scene>`` (``task/scene/crossmodal_indoor``) also selects its parent's choice,
    and an option of the rendered-database localiser (``task/localizer/...``) its task."""
    chosen = [f"{group}={option}" if group in DEFAULTS else f"+{group}={option}"]
    parent, _, leaf = group.rpartition("/")
    if leaf == "scene" and parent:
        chosen.insert(0, f"{parent}={option.rsplit('_', 1)[0]}")
    if group.startswith("task/localizer/"):
        chosen.insert(0, "task=crossmodal")
    return chosen


def _sweep_params(group: str, option: str) -> dict[str, str]:
    """The ``hydra.sweeper.params`` of an option's YAML (experiments declare their sweeps)."""
    node = OmegaConf.load(CONF_DIR / group / f"{option}.yaml")
    params = OmegaConf.select(node, "hydra.sweeper.params", default=None)
    return {} if params is None else {str(k): str(v) for k, v in params.items()}


@pytest.mark.parametrize(("group", "option", "scene"), CASES, ids="-".join)
def test_every_group_option_composes_with_every_scene(group: str, option: str, scene: str):
    overrides = [f"scene={scene}", *_overrides(group, option)]
    cfg = to_object(compose_config(overrides))
    assert cfg.scene.name in SCENES
    assert isinstance(cfg.db.features, XFeatConfig | OrbConfig)
    assert isinstance(cfg.reloc.retriever, NetVLADConfig | BowConfig)
    # An experiment's sweep names real keys: its first point composes too.
    for key, values in _sweep_params(group, option).items():
        first = values.split(",")[0]
        assert to_object(compose_config([*overrides, f"{key}={first}"]))


def test_the_group_files_of_the_defaults_list_exist():
    groups = {group for group, _ in _options()}
    assert DEFAULTS - {"diffloc_schema"} <= groups
    assert {"features", "retriever", "matcher", "optim", "map", "experiment"} <= groups


@pytest.mark.parametrize(
    ("scene", "theta_dist_m", "voxel_size_m"), [("indoor", 0.3, 0.05), ("outdoor", 0.8, 0.1)]
)
def test_map_and_reloc_settings_follow_the_scene_kind(scene, theta_dist_m, voxel_size_m):
    cfg = to_object(compose_config([f"scene={scene}"]))
    assert cfg.reloc.validation.theta_dist_m == theta_dist_m
    assert cfg.map.voxel_size_m == voxel_size_m
    explicit = to_object(compose_config(["scene=indoor", "map/scene=surfel_outdoor"]))
    assert explicit.map.voxel_size_m == 0.1


@pytest.mark.parametrize(
    ("scene", "cell_size_m", "spacing_m", "loose_m"),
    [("indoor", 0.05, 1.0, 1.0), ("outdoor", 0.2, 4.0, 2.0)],
)
def test_crossmodal_render_poses_follow_the_scene_kind(scene, cell_size_m, spacing_m, loose_m):
    task = to_object(compose_config([f"scene={scene}", "task=crossmodal", "map=tls"])).task
    assert (task.poses.cell_size_m, task.poses.spacing_m, task.loose_m) == (
        cell_size_m,
        spacing_m,
        loose_m,
    )
    explicit = compose_config(["scene=indoor", "task=crossmodal", "task/scene=crossmodal_outdoor"])
    assert to_object(explicit).task.poses.spacing_m == 4.0


@pytest.mark.parametrize(
    ("scene", "rho_max", "visibility_radius"), [("indoor", 12.0, 8), ("outdoor", 8.0, 0)]
)
def test_the_tls_render_settings_follow_the_scene_kind(scene, rho_max, visibility_radius):
    """Indoors the TLS map renders 12-px splats through the visibility filter at radius 8
    (``map/scene/tls_indoor.yaml``); outdoors, not measured, the map's own 8 px and no filter."""
    cfg = to_object(compose_config([f"scene={scene}", "task=crossmodal", "map=tls"]))
    assert (cfg.map.rho_max, cfg.map.visibility_radius) == (rho_max, visibility_radius)
    assert (cfg.map.visibility() is None) == (visibility_radius == 0)


@pytest.mark.parametrize(
    ("scene", "option", "radius_m"),
    [
        ("indoor", "tls", 0.1),
        ("indoor", "cloud", 0.3),
        ("indoor", "mesh", 0.3),
        ("indoor", "nerf", 0.3),
        ("outdoor", "tls", 0.4),
        ("outdoor", "mesh", 0.4),
    ],
)
def test_the_floor_closing_of_the_render_poses_follows_the_point_map(scene, option, radius_m):
    cfg = to_object(compose_config([f"scene={scene}", "task=crossmodal", f"map={option}"]))
    assert cfg.task.poses_for(cfg.map.point_map).floor_closing_radius_m == radius_m
    mesh_of_tls = compose_config(
        [f"scene={scene}", "task=crossmodal", "map=mesh", "map.point_map=tls_map"]
    )
    tls = to_object(mesh_of_tls).task.poses_for("tls_map").floor_closing_radius_m
    assert tls == (0.1 if scene == "indoor" else 0.4)


@pytest.mark.parametrize(
    ("option", "theta_in", "min_photometric", "max_plane_share", "ambiguity_ratio"),
    [
        ("tls", 150, 0.3, 0.95, 0.8),
        ("cloud", 150, 0.4, 0.95, 0.7),
        ("mesh", 150, 0.4, 0.95, 0.7),
        ("images", 150, 0.7, None, 0.7),
        ("nerf", 150, None, None, 0.7),
    ],
)
def test_the_validation_thresholds_follow_the_map_indoors(
    option, theta_in, min_photometric, max_plane_share, ambiguity_ratio
):
    task = to_object(compose_config(["scene=indoor", "task=crossmodal", f"map={option}"])).task
    validation = task.localizer_for(option).validation
    got = (
        validation.theta_in,
        validation.min_photometric,
        validation.max_plane_share,
        validation.ambiguity_ratio,
    )
    assert got == (theta_in, min_photometric, max_plane_share, ambiguity_ratio)
    override = f"++task.validation.{option}.theta_in=60" if option in task.validation else None
    if override:
        changed = to_object(
            compose_config(["scene=indoor", "task=crossmodal", f"map={option}", override])
        ).task
        assert changed.localizer_for(option).validation.theta_in == 60
        assert changed.localizer.validation.theta_in == 150


@pytest.mark.parametrize(
    ("scene", "contracted", "max_range_m", "box_range_m", "overlap_m", "encoding", "log2_rows"),
    [
        ("indoor", False, 10.0, 0.0, 1.0, "triplane", 17),
        ("outdoor", True, 80.0, 15.0, 4.0, "hashgrid", 19),
    ],
)
def test_nerf_settings_follow_the_scene_kind(
    scene, contracted, max_range_m, box_range_m, overlap_m, encoding, log2_rows
):
    nerf = nerf_settings(scene)
    assert nerf == to_object(compose_config([f"scene={scene}", "task=train_nerf"])).nerf
    assert nerf_settings(scene, ["nerf.submap=2"]).submap == 2
    assert nerf.train.field.contracted is contracted
    assert nerf.train.field.encoding == encoding
    assert nerf.train.field.hash_log2_table_size == log2_rows
    assert (nerf.data.lidar_max_range_m, nerf.data.box_range_m) == (max_range_m, box_range_m)
    assert nerf.submaps.overlap_m == overlap_m
    explicit = compose_config(["scene=indoor", "task=train_nerf", "nerf/scene=silvr_outdoor"])
    assert to_object(explicit).nerf.train.field.contracted is True
    assert to_object(explicit).nerf.train.field.encoding == "hashgrid"


def test_outdoor_submaps_overlap_at_the_outdoor_frame_spacing():
    """The outdoor mapping run takes a frame every 2 m: neighbouring submaps must share frames
    (with the indoor overlap of 1 m they shared none)."""
    spacing_m = 4.0 / 2.0  # scene outdoor: trajectory.speed_mps / frame_rate_hz
    T_wc = torch.eye(4, dtype=torch.float64).repeat(40, 1, 1)
    T_wc[:, 0, 3] = torch.arange(40, dtype=torch.float64) * spacing_m
    nerf = to_object(compose_config(["scene=outdoor", "task=train_nerf"])).nerf
    submaps = cluster_trajectory(T_wc, nerf.submaps)
    assert len(submaps) == nerf.submaps.num_submaps
    for a, b in itertools.pairwise(sorted(submaps, key=lambda s: s.core[0])):
        assert set(a.frames) & set(b.frames)


def test_group_options_swap_the_classes_by_target():
    cfg = to_object(compose_config(["features=orb", "retriever=bow", "matcher=mnn"]))
    assert type(cfg.db.features) is OrbConfig and type(cfg.reloc.retriever) is BowConfig
    assert cfg.reloc.method.ratio is None and cfg.reloc.method.projection_ratio is None
    default = to_object(compose_config([]))
    assert type(default.db.features) is XFeatConfig and default.db.features.max_keypoints == 1000
    assert type(default.reloc.retriever) is NetVLADConfig and default.reloc.method.ratio == 0.9


def test_an_experiment_carries_its_overrides_and_sweep():
    cfg = compose_config(["+experiment=table2_ablation_orb"])
    assert cfg.task.name == "relocalize" and type(to_object(cfg.db).features) is OrbConfig
    assert _sweep_params("experiment", "table3_noise") == {
        "db.noise_sigma": "0,0.2,0.4",
        "task.optimize": "true,false",
    }
    # The prior follows each job's noise (the oracle setting of Table III).
    noisy = compose_config(["+experiment=table3_noise", "db.noise_sigma=0.4"])
    assert to_object(noisy.db).pose_prior_sigma_m == 0.4


def test_an_unknown_target_field_is_refused():
    with pytest.raises(UnknownKeyError, match="db.features.max_keypoints"):
        compose_config(["features=orb", "+db.features.max_keypoint=5"])

"""COLMAP TEXT export of a visual database, read back with pycolmap."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch

from diffloc.database.colmap import COLMAP_PIXEL_OFFSET, reprojection_errors, write_colmap_text
from diffloc.database.database import VisualDatabase
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import invert, se3_exp

POINTS = 20


def camera(fx: float) -> PinholeCamera:
    f64 = torch.float64
    return PinholeCamera(
        fx=torch.tensor(fx, dtype=f64),
        fy=torch.tensor(101.5, dtype=f64),
        cx=torch.tensor(79.25, dtype=f64),
        cy=torch.tensor(60.5, dtype=f64),
        width=160,
        height=120,
    )


def make_database(seed: int = 0) -> VisualDatabase:
    """3 keyframes (2 distinct cameras) seeing 20 points with pixel noise; point 7 unobserved."""
    generator = torch.Generator().manual_seed(seed)
    db = VisualDatabase(descriptor_dim=4)
    positions = torch.randn(POINTS, 3, generator=generator, dtype=torch.float64) * 0.5
    positions[:, 2] += 5.0
    ids = db.add_points(positions, torch.randn(POINTS, 4, generator=generator), -torch.ones(20))
    for k in range(3):
        T_wc = se3_exp(torch.randn(6, generator=generator, dtype=torch.float64) * 0.1)
        cam = camera(100.0 + k % 2)
        uv, _ = cam.project_world(positions, T_wc)
        noise = torch.randn(POINTS, 2, generator=generator) * 0.5
        unmatched = torch.rand(3, 2, generator=generator) * 100
        keypoints = torch.cat([unmatched, uv.float() + noise])  # points start at keypoint 3
        db.add_keyframe(
            T_wc, cam, keypoints, torch.randn(23, 4, generator=generator), torch.ones(23)
        )
        seen = torch.tensor([p for p in range(k, POINTS, k + 1) if p != 7])
        db.add_observations(k, seen + 3, ids[seen])
    return db


def test_export_reads_back_in_pycolmap_with_the_same_model(tmp_path: Path):
    db = make_database()
    names = [f"seq/rgb/{k:06d}.png" for k in range(3)]
    colors = np.arange(3 * POINTS, dtype=np.uint8).reshape(POINTS, 3)
    write_colmap_text(db, tmp_path / "sparse", names, colors)
    assert sorted(p.name for p in (tmp_path / "sparse").iterdir()) == [
        "cameras.txt",
        "images.txt",
        "points3D.txt",
    ]
    model = pycolmap.Reconstruction(tmp_path / "sparse")
    assert len(model.cameras) == 2 and len(model.images) == 3
    T_cw = invert(db.T_wc).numpy()
    offsets = db.keypoint_offsets.tolist()
    for k in range(3):
        image = model.images[k + 1]
        assert image.name == names[k]
        np.testing.assert_allclose(image.cam_from_world().matrix(), T_cw[k, :3], rtol=0, atol=1e-9)
        cam = image.camera
        assert cam.model == pycolmap.CameraModelId.PINHOLE
        assert (cam.width, cam.height) == (160, 120)
        fx, fy, cx, cy = db.intrinsics[k].tolist()
        np.testing.assert_array_equal(cam.params, [fx, fy, cx + 0.5, cy + 0.5])
        xy = np.array([p.xy for p in image.points2D])
        np.testing.assert_array_equal(xy, db.keypoints[offsets[k] : offsets[k + 1]].double() + 0.5)
        ids = [p.point3D_id if p.has_point3D() else -1 for p in image.points2D]
        expected = db.keypoint_points[offsets[k] : offsets[k + 1]]
        assert ids == torch.where(expected >= 0, expected + 1, -1).tolist()

    tracks = {
        (element.image_id - 1, offsets[element.image_id - 1] + element.point2D_idx, point_id - 1)
        for point_id, point in model.points3D.items()
        for element in point.track.elements
    }
    assert tracks == {tuple(row) for row in db.observations().tolist()}
    assert 8 not in model.points3D  # point 7 has no observation
    assert len(model.points3D) == POINTS - 1

    errors = reprojection_errors(db)
    rows = db.observations()
    for k in range(db.num_keyframes):  # the database's own camera model gives the same errors
        mine = rows[:, 0] == k
        uv, _ = db.camera(k).project_world(db.point_positions[rows[mine, 2]], db.T_wc[k])
        own = (uv - db.keypoints[rows[mine, 1]].double()).norm(dim=1)
        torch.testing.assert_close(errors[mine], own, rtol=0, atol=1e-9)
    by_observation = dict(zip(map(tuple, db.observations().tolist()), errors.tolist(), strict=True))
    colmap_errors = []
    for point_id, point in model.points3D.items():
        np.testing.assert_array_equal(point.xyz, db.point_positions[point_id - 1].numpy())
        np.testing.assert_array_equal(point.color, colors[point_id - 1])
        track_errors = []
        for element in point.track.elements:
            image = model.images[element.image_id]
            projected = image.camera.img_from_cam(image.cam_from_world() * point.xyz)
            error = np.linalg.norm(projected - image.points2D[element.point2D_idx].xy)
            k = element.image_id - 1
            ours = by_observation[(k, offsets[k] + element.point2D_idx, point_id - 1)]
            assert error == pytest.approx(ours, abs=1e-6)
            track_errors.append(error)
        assert point.error == pytest.approx(np.mean(track_errors), abs=1e-6)
        colmap_errors += track_errors
    assert np.mean(colmap_errors) == pytest.approx(float(errors.mean()), abs=1e-6)
    # COLMAP's own summary averages the stored per-point ERROR fields.
    point_errors = [point.error for point in model.points3D.values()]
    assert model.compute_mean_reprojection_error() == pytest.approx(np.mean(point_errors))


def test_pixel_offset_keeps_exact_projections_exact(tmp_path: Path):
    """Keypoints at the exact projections reproject with zero error in COLMAP's convention."""
    db = make_database(1)
    uv = torch.cat(
        [
            db.camera(k).project_world(db.point_positions, db.T_wc[k])[0]
            for k in range(db.num_keyframes)
        ]
    )
    rows = db.observations()
    db.keypoints[rows[:, 1]] = uv[rows[:, 0] * POINTS + rows[:, 2]].float()
    write_colmap_text(db, tmp_path / "m")
    model = pycolmap.Reconstruction(tmp_path / "m")
    assert COLMAP_PIXEL_OFFSET == 0.5
    assert model.compute_mean_reprojection_error() < 1e-4  # float32 keypoints
    assert float(reprojection_errors(db).max()) < 1e-4
    assert model.points3D[1].color.tolist() == [128, 128, 128]


def test_default_names_and_determinism(tmp_path: Path):
    db = make_database()
    write_colmap_text(db, tmp_path / "a")
    write_colmap_text(db, tmp_path / "b")
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    model = pycolmap.Reconstruction(tmp_path / "a")
    assert [model.images[k + 1].name for k in range(3)] == [
        f"keyframe_{k:06d}.png" for k in range(3)
    ]


# ---------------------------------------------------------------- one test per bad-input rule


def test_non_empty_output_folder_needs_overwrite(tmp_path: Path):
    db = make_database()
    out = tmp_path / "sparse"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match=r"sparse exists and is not empty; pass overwrite"):
        write_colmap_text(db, out)
    assert [p.name for p in out.iterdir()] == ["notes.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sparse"]  # no temporary folder left
    write_colmap_text(db, out, overwrite=True)
    assert sorted(p.name for p in out.iterdir()) == ["cameras.txt", "images.txt", "points3D.txt"]


def test_empty_output_folder_is_used(tmp_path: Path):
    (tmp_path / "sparse").mkdir()
    write_colmap_text(make_database(), tmp_path / "sparse")
    assert len(pycolmap.Reconstruction(tmp_path / "sparse").images) == 3


def test_output_path_that_is_a_file(tmp_path: Path):
    (tmp_path / "sparse").write_text("x")
    with pytest.raises(FileExistsError, match="is not a folder"):
        write_colmap_text(make_database(), tmp_path / "sparse", overwrite=True)


@pytest.mark.parametrize(
    ("names", "message"),
    [
        (["a.png", "b.png"], "2 image names for 3 keyframes"),
        (["a.png", "b c.png", "d.png"], "whitespace"),
        (["a.png", "a.png", "d.png"], "distinct"),
    ],
)
def test_bad_image_names(tmp_path: Path, names: list[str], message: str):
    with pytest.raises(ValueError, match=message):
        write_colmap_text(make_database(), tmp_path / "m", names)
    assert not (tmp_path / "m").exists()


def test_bad_point_colors(tmp_path: Path):
    with pytest.raises(ValueError, match="uint8"):
        write_colmap_text(make_database(), tmp_path / "m", point_colors=np.zeros((POINTS, 3)))
    assert not (tmp_path / "m").exists()


def test_non_finite_database(tmp_path: Path):
    db = make_database()
    db.point_positions[3, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite point_positions"):
        write_colmap_text(db, tmp_path / "m")
    assert not (tmp_path / "m").exists()


def test_point_behind_an_observing_camera(tmp_path: Path):
    db = make_database()
    db.point_positions[0] = invert(db.T_wc[0])[:3, :3].T @ torch.tensor([0.0, 0.0, -1.0]).double()
    db.point_positions[0] += db.T_wc[0, :3, 3]
    with pytest.raises(ValueError, match="behind a keyframe"):
        write_colmap_text(db, tmp_path / "m")
    assert not (tmp_path / "m").exists()

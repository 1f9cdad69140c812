"""``task=train_nerf`` scores its field on the held-out frames: finite scores in the record
(those of the exported field), a null with its reason when nothing is held out, the printed
line, and scoring that leaves the trained weights as they were."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from diffloc.config import compose_config, to_object
from diffloc.eval.field_scores import heldout_field_scores
from diffloc.io.dataset import read_sequence
from diffloc.maps.nerf.data import build_submap_rays
from diffloc.maps.nerf.export import load_field
from diffloc.maps.nerf.renderer import render_image
from diffloc.maps.nerf.submaps import cluster_trajectory
from diffloc.maps.nerf.train import fit_submap
from diffloc.pipeline import nerf_stage
from diffloc.pipeline.nerf_heldout import HELDOUT_KEYS, heldout_scores
from diffloc.pipeline.nerf_stage import train_nerf_submap
from tests.conftest import TINY_NERF, run_task

HOLDOUT_4 = [o for o in TINY_NERF if not o.startswith("nerf.data.holdout_every=")] + [
    "nerf.data.holdout_every=4"
]
"""``TINY_NERF`` holding out frame 0 of the tiny scene's submap 0 (frames 0-3; trains on 1-3)."""


def _record(nerf_dir: Path) -> dict:
    return json.loads((nerf_dir / "submap_0" / "train_nerf.json").read_text(encoding="utf-8"))


def test_the_record_holds_finite_held_out_scores_of_the_exported_field(
    tiny_indoor_dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "nerf"
    summary = run_task("train_nerf", tiny_indoor_dataset, *HOLDOUT_4, f"nerf.out_dir={out}")
    record = _record(out)
    assert record["heldout_frames"] == 1 and record["heldout_scores"] == summary.heldout_scores
    scores = record["heldout_scores"]
    assert set(scores) == set(HELDOUT_KEYS)
    assert all(math.isfinite(scores[key]) for key in HELDOUT_KEYS)
    assert scores["depth_median_abs_err_m"] >= 0 and 0 <= scores["normal_median_err_deg"] <= 180
    assert "1 held-out frame(s) at 40x30" in record["heldout_note"]
    assert f"held-out: PSNR {scores['psnr_heldout_db']:.2f} dB" in capsys.readouterr().out

    # the scores are those of the committed field, scored again from its files
    field, grid = load_field(out / "submap_0" / "field")
    cfg = to_object(compose_config(["task=train_nerf", *HOLDOUT_4]).nerf)
    seq = read_sequence(tiny_indoor_dataset, "mapping")
    camera = seq.camera.scaled(cfg.data.image_scale)
    again = heldout_field_scores(field, grid, seq, camera, [0], full=True)
    assert {key: again[key] for key in HELDOUT_KEYS} == pytest.approx(scores, rel=1e-5)

    # the surface / sky split of the right half pools back to the frame's PSNR
    gt = F.interpolate(seq.load_depth(0)[None], size=(camera.height, camera.width))
    gt = gt[0, 0, :, camera.width // 2 :]
    n_surface = int((gt > 0).sum())
    n_sky = gt.numel() - n_surface
    assert n_surface > 0 and (again["psnr_heldout_sky_db"] is None) == (n_sky == 0)
    total = n_surface * _mse(again["psnr_heldout_surface_db"])
    if n_sky:
        total += n_sky * _mse(again["psnr_heldout_sky_db"])
    assert total / gt.numel() == pytest.approx(_mse(again["psnr_heldout_db"]), rel=1e-4)

    # the sky opacity is the mean rendered opacity of the (whole) image's pixels without depth
    sky = F.interpolate(seq.load_depth(0)[None], size=(camera.height, camera.width))[0, 0] <= 0
    code = field.appearance.weight[0].detach()  # opacity does not depend on the code
    opacity = render_image(field, grid, camera, seq.T_wc[0].float(), code)["opacity"][0]
    if sky.any():
        assert again["sky_opacity_mean"] == pytest.approx(float(opacity[sky].mean()), rel=1e-5)
    else:
        assert again["sky_opacity_mean"] is None


def _mse(psnr_db: float) -> float:
    return 10 ** (-psnr_db / 10)


def test_without_held_out_frames_the_record_says_why_and_nothing_crashes(
    tiny_indoor_dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "nerf"
    summary = run_task("train_nerf", tiny_indoor_dataset, *TINY_NERF, f"nerf.out_dir={out}")
    record = _record(out)
    assert record["heldout_frames"] == 0 and record["heldout_scores"] is None
    assert "holdout_every=0" in record["heldout_note"] == summary.heldout_note
    assert "held-out: not scored: nerf.data.holdout_every=0" in capsys.readouterr().out


def test_a_sequence_without_depth_images_gets_psnr_only(
    tiny_indoor_dataset: Path, tmp_path: Path
) -> None:
    cfg = to_object(compose_config(["task=train_nerf", *HOLDOUT_4]).nerf)
    seq = read_sequence(tiny_indoor_dataset, "mapping")
    seq.depth_paths = None
    frames = cluster_trajectory(seq.T_wc, cfg.submaps)[0].frames
    rays = build_submap_rays(seq, frames, cfg.data)
    module = fit_submap(rays, cfg.train, tmp_path, 1, show_progress=False)
    scores, note = heldout_scores(module.field, module.grid, seq, rays, 4)
    assert math.isfinite(scores["psnr_heldout_db"])
    assert scores["depth_median_abs_err_m"] is None and scores["normal_median_err_deg"] is None
    assert "has no depth images" in note


def test_scoring_leaves_the_trained_weights_unchanged(
    tiny_indoor_dataset: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    seen = []

    def checked(field, grid, *args):
        modules = (field, grid)
        before = [{k: v.clone() for k, v in m.state_dict().items()} for m in modules]
        grads = [None if p.grad is None else p.grad.clone() for p in field.parameters()]
        training = field.training
        result = heldout_scores(field, grid, *args)
        for m, state in zip(modules, before, strict=True):
            after = m.state_dict()
            assert after.keys() == state.keys()
            assert all(torch.equal(after[k], state[k]) for k in state), "scoring changed weights"
        for p, g in zip(field.parameters(), grads, strict=True):
            assert (p.grad is None and g is None) or torch.equal(p.grad, g)
        assert field.training == training
        seen.append(result)
        return result

    monkeypatch.setattr(nerf_stage, "heldout_scores", checked)
    cfg = to_object(compose_config(["task=train_nerf", *HOLDOUT_4, f"nerf.out_dir={tmp_path}"]))
    summary = train_nerf_submap(tiny_indoor_dataset, cfg.nerf, False)
    assert len(seen) == 1 and summary.heldout_scores == pytest.approx(seen[0][0])

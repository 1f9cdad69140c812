"""NetVLAD of a rendered database tuned on the mapping images: what it learns, its stage, bad
input.

The tiny scene's five mapping images are the real images and renders of its mesh at the same
five views are the database; both get poses 3 m apart on a line (labels only), so each real
image has exactly one positive render (its own view) and four negatives (beyond 2 m).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.crossmodal.database import DatabaseConfig, build_database
from diffloc.crossmodal.retrieval_tuning import (
    RetrievalTuningConfig,
    tune_on_dense_maps,
    tune_render_retrieval,
)
from diffloc.crossmodal.synthesize import MeshMap, render_views
from diffloc.features.dense import DenseXFeat
from diffloc.features.netvlad_training import FinetuneConfig, TripletConfig
from diffloc.io.dataset import read_sequence
from diffloc.io.mesh_obj import read_textured_mesh_obj
from diffloc.pipeline import crossmodal_retrieval
from diffloc.pipeline.crossmodal_retrieval import tune_retrieval_stage
from diffloc.pipeline.stage import StageOutcome

CONFIG = RetrievalTuningConfig(
    finetune=FinetuneConfig(
        epochs=5,
        batch_size=4,
        learning_rate=1e-2,
        margin=1.0,
        triplets=TripletConfig(negative_distance_m=2.0, num_negatives=2),
    )
)


def _line_poses(n: int) -> torch.Tensor:
    T_wc = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    T_wc[:, 0, 3] = 3.0 * torch.arange(n, dtype=torch.float64)
    return T_wc


@pytest.fixture(scope="module")
def scene(tiny_indoor_dataset):
    """(database of mesh renders, mapping images, their poses), poses on a line."""
    mapping = read_sequence(tiny_indoor_dataset, "mapping")
    mesh = MeshMap(read_textured_mesh_obj(tiny_indoor_dataset / "map" / "mesh" / "scene.obj"))
    views = render_views(mesh, mapping.T_wc, mapping.camera, batch_size=8)
    T_wc = _line_poses(len(mapping))
    config = DatabaseConfig(max_keypoints=128, netvlad_clusters=4, samples_per_image=50)
    db = build_database(views, T_wc, mapping.camera, config, "tiny mesh")
    images = torch.stack([mapping.load_rgb(i) for i in range(len(mapping))])
    return db, images, T_wc


def test_tuning_lowers_the_cross_domain_loss_and_redescribes_the_renders(scene):
    db, images, T_wc = scene
    before = {k: v.clone() for k, v in db.netvlad.state_dict().items()}
    tuned = tune_render_retrieval(db, images, T_wc, CONFIG)
    assert tuned.mapping_images == len(images)
    # Anchors: 5 real images (one render each within 1 m / 30 deg) and 5 renders.
    assert tuned.result.num_tuples == 2 * len(images)
    assert tuned.result.final_loss < tuned.result.initial_loss
    for name, value in db.netvlad.state_dict().items():  # the input database is unchanged
        assert torch.equal(value, before[name])
    out = tuned.database
    assert out.rgb is db.rgb and out.features == db.features
    with torch.no_grad():
        expected = out.netvlad(DenseXFeat()(db.rgb).half().float())
    assert torch.allclose(out.global_descriptors, expected, atol=1e-5)
    assert not torch.allclose(out.global_descriptors, db.global_descriptors)


def test_every_other_mapping_image_trains(scene):
    db, images, T_wc = scene
    config = RetrievalTuningConfig(mapping_every=2, finetune=CONFIG.finetune)
    tuned = tune_render_retrieval(db, images, T_wc, config)
    assert tuned.mapping_images == math.ceil(len(images) / 2)


def stage_inputs(scene, tmp_path, monkeypatch) -> tuple[Path, StageOutcome]:
    """A dataset folder whose mapping run the retrieval stage reads as the scene's images and
    line poses (``read_sequence`` replaced), and a stand-in database stage outcome."""
    db, images, _ = scene
    dataset = tmp_path / "indoor"
    mapping = dataset / "mapping"
    (mapping / "rgb").mkdir(parents=True)
    for name in ("calib.yaml", "poses.txt"):
        (mapping / name).write_text(
            "stand-in: the stage reads the sequence through read_sequence\n"
        )
    rgbd = {"kind": "folder", "files": 2, "size": 1, "sha256": "0" * 64}

    class Mapping:  # what read_sequence gives the stage: images, poses, camera
        T_wc = _line_poses(len(images))
        camera = db.camera

        def __len__(self):
            return len(images)

        def load_rgb(self, i):
            return images[i]

    monkeypatch.setattr(crossmodal_retrieval, "read_sequence", lambda *_: Mapping())
    return dataset, StageOutcome(summary=None, outputs={"rgbd": rgbd})


def test_the_stage_saves_safetensors_and_reuses_them(scene, tmp_path, monkeypatch):
    db, images, _ = scene
    dataset, outcome = stage_inputs(scene, tmp_path, monkeypatch)
    first, made = tune_retrieval_stage(dataset, "mesh", CONFIG, (db, outcome))
    folder = dataset / "crossmodal" / "mesh" / "retrieval"
    assert (folder / "netvlad.safetensors").is_file()
    record = json.loads((folder / "retrieval.json").read_text())
    assert record["tuples"] == 2 * len(images) and record["final_loss"] < record["initial_loss"]
    monkeypatch.setattr(crossmodal_retrieval, "tune_render_retrieval", None)  # must not run
    again, reused = tune_retrieval_stage(dataset, "mesh", CONFIG, (db, outcome))
    assert reused.outputs == made.outputs
    assert torch.equal(again.global_descriptors, first.global_descriptors)
    for name, value in first.netvlad.state_dict().items():
        assert torch.equal(again.netvlad.state_dict()[name], value)


def test_images_of_another_size_are_refused(scene):
    db, images, T_wc = scene
    with pytest.raises(ShapeError, match="images"):
        tune_render_retrieval(db, images[..., :-8], T_wc, CONFIG)
    with pytest.raises(ShapeError, match="5 mapping images but 4 poses"):
        tune_render_retrieval(db, images, T_wc[:4], CONFIG)
    maps = torch.zeros(5, 64, 15, 20, dtype=torch.float16)
    with pytest.raises(ShapeError, match="renders"):
        tune_on_dense_maps(db, maps, T_wc, maps[:4], CONFIG)


def test_no_mapping_image_near_a_render_names_the_bounds(scene):
    db, images, T_wc = scene
    far = T_wc.clone()
    far[:, 1, 3] += 100.0  # every mapping image 100 m from every render
    with pytest.raises(ValueError, match=r"no mapping image pairs .*finetune\.triplets"):
        tune_render_retrieval(db, images, far, CONFIG)


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="mapping_every"):
        RetrievalTuningConfig(mapping_every=0)

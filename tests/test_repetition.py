"""Repeated structure under a relocalised pose (diffloc.reloc.repetition) and its use in the
pose validation."""

import math

import pytest
import torch
import torch.nn.functional as F

from diffloc.pipeline.reloc_stage import RelocStageConfig
from diffloc.reloc.hierarchical import RelocConfig
from diffloc.reloc.repetition import RepetitionConfig, repeated_shift
from diffloc.reloc.validation import PoseEvidence, PoseValidator, ValidationConfig

PERIOD_M = 1.25


def tiled_floor_and_objects(generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """A map of a floor whose texture repeats every ``PERIOD_M`` along x (20 texture spots per
    tile, 8 tiles: equal descriptors at equal spots) and 40 distinct objects; positions (P, 3)
    and unit descriptors (P, 32)."""
    spots = torch.rand(20, 2, generator=generator) * PERIOD_M
    spot_descriptors = F.normalize(torch.randn(20, 32, generator=generator), dim=1)
    tiles = torch.arange(8, dtype=torch.float64) * PERIOD_M
    floor = torch.stack(
        [
            (spots[None, :, 0] + tiles[:, None]).flatten(),
            spots[None, :, 1].expand(8, -1).flatten(),
            torch.zeros(160, dtype=torch.float64),
        ],
        1,
    )
    objects = torch.rand(40, 3, generator=generator, dtype=torch.float64) * 10
    positions = torch.cat([floor, objects])
    descriptors = torch.cat(
        [
            spot_descriptors.repeat(8, 1),
            F.normalize(torch.randn(40, 32, generator=generator), dim=1),
        ]
    )
    return positions, descriptors


@pytest.fixture
def scene():
    generator = torch.Generator().manual_seed(3)
    positions, descriptors = tiled_floor_and_objects(generator)
    return positions, descriptors, generator


def test_inliers_on_a_tiled_floor_repeat_by_whole_periods(scene):
    positions, descriptors, _ = scene
    points = torch.arange(60, 80)  # the 20 spots of tile 3
    shift = repeated_shift(points, positions, descriptors, "l2", RepetitionConfig())
    assert shift.support == 20
    periods = shift.shift_m / PERIOD_M
    assert periods == pytest.approx(round(periods), abs=1e-9) and round(periods) >= 1


def test_distinct_inliers_have_no_common_shift_and_a_mix_counts_the_floor(scene):
    positions, descriptors, _ = scene
    objects = torch.arange(160, 200)
    config = RepetitionConfig()
    # twins of distinct points are random points; their shifts agree only by chance
    assert repeated_shift(objects, positions, descriptors, "l2", config).support <= 4
    mixed = torch.cat([objects[:30], torch.arange(60, 70)])
    assert 10 <= repeated_shift(mixed, positions, descriptors, "l2", config).support <= 14


def test_twins_nearer_than_the_smallest_shift_do_not_count(scene):
    positions, descriptors, _ = scene
    points = torch.arange(60, 80)
    config = RepetitionConfig(min_shift_m=PERIOD_M * 8.5)  # farther than the floor reaches
    assert repeated_shift(points, positions, descriptors, "l2", config).support <= 5


def test_a_floor_of_distinct_spots_does_not_repeat(scene):
    positions, descriptors, generator = scene
    points = torch.arange(60, 80)
    distinct = descriptors.clone()
    distinct[:160] = F.normalize(torch.randn(160, 32, generator=generator), dim=1)
    assert repeated_shift(points, positions, distinct, "l2", RepetitionConfig()).support <= 5


def test_binary_descriptors_repeat_by_hamming_distance():
    positions = torch.tensor([[0.0, 0, 4], [2.0, 0, 4], [4.0, 0, 4], [1.0, 3, 4]])
    descriptors = torch.tensor([[0b1010], [0b1011], [0b0101], [0b0100]], dtype=torch.uint8)
    shift = repeated_shift(
        torch.tensor([0]), positions, descriptors, "hamming", RepetitionConfig(max_twins=1)
    )
    assert (shift.support, shift.shift_m) == (1, 2.0)


def test_no_inliers_give_no_repetition(scene):
    positions, descriptors, _ = scene
    empty = torch.zeros(0, dtype=torch.int64)
    shift = repeated_shift(empty, positions, descriptors, "l2", RepetitionConfig())
    assert (shift.support, shift.shift_m) == (0, 0.0)


def test_bad_inputs_are_refused(scene):
    positions, descriptors, _ = scene
    config = RepetitionConfig()
    with pytest.raises(IndexError, match="map points"):
        repeated_shift(torch.tensor([0, 500]), positions, descriptors, "l2", config)
    with pytest.raises(ValueError, match="199 point descriptors for 200 positions"):
        repeated_shift(torch.tensor([0]), positions, descriptors[1:], "l2", config)


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [
        ({"min_shift_m": -1.0}, "min_shift_m"),
        ({"tolerance_m": math.nan}, "tolerance_m"),
        ({"max_twins": 0}, "max_twins"),
    ],
)
def test_bad_settings_name_the_key(kwargs, key):
    with pytest.raises(ValueError, match=f"repetition.{key}"):
        RepetitionConfig(**kwargs)


def evidence(repeated: int | None) -> PoseEvidence:
    return PoseEvidence(
        torch.zeros(3, dtype=torch.float64), 100, 200, 1.0, ((100, 0.0),), None, repeated
    )


def test_validation_refuses_repeated_and_unmeasured_poses():
    validator = PoseValidator(ValidationConfig(temporal=False, max_repeated=0.5))
    assert validator.validate_evidence(evidence(50), 0.0)
    assert not validator.validate_evidence(evidence(51), 1.0)
    with pytest.raises(ValueError, match="max_repeated"):
        validator.validate_evidence(evidence(None), 2.0)
    seed1 = PoseValidator(ValidationConfig(temporal=False, max_repeated=0.5).seed1_rule())
    assert seed1.validate_evidence(evidence(90), 0.0)
    assert PoseValidator(ValidationConfig(temporal=False)).validate_evidence(evidence(None), 0.0)


def test_records_carry_the_repetition():
    record = {
        "found": True,
        "position_m": [0.0, 0.0, 0.0],
        "candidates": [{"inliers": 50, "matches": 80, "coverage": 0.8, "distance_to_chosen_m": 0}],
    }
    assert PoseEvidence.from_record(record).repeated is None
    repeated = {**record, "repetition": {"support": 12, "shift_m": 1.25}}
    assert PoseEvidence.from_record(repeated).repeated == 12


@pytest.mark.parametrize("value", [-0.1, 1.5, math.nan])
def test_a_bad_threshold_is_refused(value):
    with pytest.raises(ValueError, match="max_repeated"):
        ValidationConfig(max_repeated=value)


def test_the_test_needs_map_points_and_says_so_before_any_work():
    with pytest.raises(ValueError, match="points=naive"):
        RelocStageConfig(
            method=RelocConfig(points="naive"), validation=ValidationConfig(max_repeated=0.2)
        )
    RelocStageConfig(method=RelocConfig(points="naive"))  # without the test: fine

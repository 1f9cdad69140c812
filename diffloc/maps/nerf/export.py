"""Trained fields on disk without pickle: ``field.safetensors`` (weights and density grid) and
``field.json`` (``format_version``, the network and sampler settings, the box)."""

from __future__ import annotations

import json
import os
from dataclasses import asdict, fields
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load as load_safetensors
from safetensors.torch import save as save_safetensors

from diffloc.io.atomic import atomic_directory
from diffloc.io.json_record import read_json_record
from diffloc.maps.nerf.field import FieldConfig, RadianceField
from diffloc.maps.nerf.sampler import DensityGrid, SamplerConfig

__all__ = ["FORMAT_VERSION", "export_field", "load_field"]

FORMAT_VERSION = 1


def export_field(
    out_dir: str | os.PathLike, field: RadianceField, grid: DensityGrid, overwrite: bool = False
) -> Path:
    """Write a field and its density grid into the folder ``out_dir`` (atomically).

    Returns:
        ``out_dir``.
    """
    tensors = {f"field.{k}": v.detach().contiguous() for k, v in field.state_dict().items()}
    tensors |= {f"grid.{k}": v.detach().contiguous() for k, v in grid.state_dict().items()}
    record = {
        "format_version": FORMAT_VERSION,
        "field": asdict(field.config),
        "sampler": asdict(grid.config),
        "num_images": field.appearance.num_embeddings,
    }
    with atomic_directory(out_dir, overwrite=overwrite) as tmp:
        (tmp / "field.safetensors").write_bytes(save_safetensors(tensors))
        (tmp / "field.json").write_text(json.dumps(record, indent=1))
    return Path(out_dir)


def _dataclass(cls: type, values: dict, path: Path):
    known = {f.name for f in fields(cls)}
    unknown = set(values) - known
    if unknown:
        raise ValueError(f"{path}: unknown {cls.__name__} keys {sorted(unknown)}")
    return cls(**values)


def _box(tensors: dict[str, torch.Tensor], path: Path) -> tuple[torch.Tensor, torch.Tensor]:
    """The (3,) lower and upper corners of the box saved with a field's weights (the
    tri-plane's per-axis vertex counts depend on it)."""
    try:
        centre, half = tensors["field.normalise.centre"], tensors["field.normalise.half_extent"]
    except KeyError as error:
        raise ValueError(f"{path}: no field box ({error.args[0]} missing)") from error
    if centre.shape != (3,) or half.shape != (3,) or not bool(torch.isfinite(centre).all()):
        raise ValueError(f"{path}: the field box is not two finite (3,) vectors")
    if not bool((half > 0).all() & torch.isfinite(half).all()):
        raise ValueError(f"{path}: the field box has a side that is not positive and finite")
    return centre - half, centre + half


def load_field(in_dir: str | os.PathLike) -> tuple[RadianceField, DensityGrid]:
    """Read :func:`export_field` output (no unpickling).

    Raises:
        FileNotFoundError: a file is missing.
        ValueError: a foreign or corrupt file, or weights that do not fit the settings.
    """
    in_dir = Path(in_dir)
    meta, weights = in_dir / "field.json", in_dir / "field.safetensors"
    for path in (meta, weights):
        if not path.is_file():
            raise FileNotFoundError(f"{path} does not exist")
    record = read_json_record(meta)
    if record.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"{meta}: not a diffloc field of format_version {FORMAT_VERSION}")
    try:
        tensors = load_safetensors(weights.read_bytes())
    except SafetensorError as error:
        raise ValueError(f"{weights}: not a safetensors file ({error})") from error
    field_cfg = _dataclass(FieldConfig, record["field"], meta)
    grid = DensityGrid(_dataclass(SamplerConfig, record["sampler"], meta))
    field = RadianceField(field_cfg, *_box(tensors, weights), int(record["num_images"]))
    for module, prefix in ((field, "field."), (grid, "grid.")):
        state = {k[len(prefix) :]: v for k, v in tensors.items() if k.startswith(prefix)}
        try:
            module.load_state_dict(state)
        except RuntimeError as error:
            raise ValueError(f"{weights}: weights do not fit {meta} ({error})") from error
        if not all(bool(torch.isfinite(v).all()) for v in state.values() if v.is_floating_point()):
            raise ValueError(f"{weights}: non-finite weights")
    return field, grid

"""How full the hash grid's tables are on a submap (issue 19): for each level, the box's cell
size (cm per axis) and the number of cells holding at least one of the submap's lidar
returns, against the level's rows. A surface sheet of ``n`` cells touches about ``2 n``
vertices, so a hashed level whose count nears its rows is shared by colliding vertices.

    PYTHONPATH=. OMP_NUM_THREADS=1 python3 experiments/nerf_hash_occupancy.py --scene outdoor \\
        --data data/outdoor_seed0 [--override nerf.train.field.hash_log2_table_size=19]
"""

from __future__ import annotations

import argparse

import torch

from diffloc.config import nerf_settings
from diffloc.maps.nerf.contraction import SceneNormalisation
from diffloc.maps.nerf.encodings import HashGridEncoding
from diffloc.pipeline.nerf_stage import submap_training_data


def occupied_cells(xyz: torch.Tensor, resolution: int) -> int:
    """Distinct cells of a grid of ``resolution`` vertices per axis holding at least one of the
    (N, 3) points in [-1, 1]^3."""
    cell = ((xyz.clamp(-1.0, 1.0) + 1.0) * (0.5 * (resolution - 1))).floor().long()
    return len(torch.unique(cell.clamp(max=resolution - 2), dim=0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", choices=("indoor", "outdoor"), default="indoor")
    parser.add_argument("--data", required=True)
    parser.add_argument("--submap", type=int, default=0)
    parser.add_argument("--override", nargs="+", default=[])
    args = parser.parse_args()
    nerf = nerf_settings(args.scene, [f"nerf.submap={args.submap}", *args.override])
    _, _, rays = submap_training_data(args.data, nerf)
    lidar = rays.lidar
    points = lidar.origins + lidar.directions * lidar.ranges[:, None]
    field = nerf.train.field
    xyz = SceneNormalisation(rays.box_min, rays.box_max, field.contracted)(points)[0]
    encoding = HashGridEncoding(
        field.hash_levels,
        field.hash_channels,
        field.hash_log2_table_size,
        field.hash_base_resolution,
        field.hash_max_resolution,
        field.init_std,
    )
    extent = (rays.box_max - rays.box_min).tolist()
    # the box spans the cube (R - 1 cells per side), with the contraction its half
    box_share = 0.5 if field.contracted else 1.0
    print(f"box {[round(e, 2) for e in extent]} m, {len(points)} lidar returns")
    print("| vertices per axis | cell in the box (cm) | rows | kind | cells with a return |")
    print("|---|---|---|---|---|")
    for table, r in zip(encoding.tables, encoding.resolutions, strict=True):
        cm = " x ".join(f"{100 * e / (box_share * (r - 1)):.1f}" for e in extent)
        kind = "dense" if len(table) == r**3 else "hashed"
        print(f"| {r} | {cm} | {len(table)} | {kind} | {occupied_cells(xyz, r)} |")


if __name__ == "__main__":
    main()

"""Cross-modal localization pieces of seed 2: render-pose selection in 3D maps."""

from diffloc.crossmodal.pose_selection import (
    VIEW_NAMES,
    FloorPlan,
    PoseSelectionConfig,
    RenderPoses,
    find_floors,
    floor_plan,
    plot_floor_plan,
    select_render_poses,
    view_poses,
    write_floor_plan_figures,
)

__all__ = [
    "VIEW_NAMES",
    "FloorPlan",
    "PoseSelectionConfig",
    "RenderPoses",
    "find_floors",
    "floor_plan",
    "plot_floor_plan",
    "select_render_poses",
    "view_poses",
    "write_floor_plan_figures",
]

"""Maps localised against: surfel maps and coloured point clouds (built, validated, stored)."""

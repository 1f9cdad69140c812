"""Visual database of keyframes and surfel-anchored map points (seed 1 Sec. III-A)."""

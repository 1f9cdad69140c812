"""Cross-modal localization pieces of seed 2: render-pose selection in 3D maps."""

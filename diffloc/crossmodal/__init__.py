"""Cross-modal localization pieces of seed 2: render-pose selection, RGB-D maps, databases."""

"""Evaluation: pose-error metrics (recall, mATE, precision-recall), held-out seed statistics and
paired bootstrap intervals over Hydra sweeps, Markdown tables, plots."""

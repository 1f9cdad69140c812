"""Evaluation: pose-error metrics (recall, mATE, precision-recall), Markdown tables, plots."""

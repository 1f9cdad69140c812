"""Pipeline stages: dataset folders in, result files out, cached; called by ``diffloc``."""

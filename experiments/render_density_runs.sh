#!/usr/bin/env bash
# The render-density runs of experiments/results/render_density_indoor_seed{0,1}.md: one
# `diffloc task=crossmodal` run per (render spacing, views per sample) cell on one dataset and
# map, every 4th frame of query_same and query_reverse, top-k 20, one thread. Each run writes
# experiments/runs/render_density/<dataset name>/<map>_s<spacing>_v<views>/results.json (the
# database's render time is its stages.database entry); experiments/render_density_table.py
# turns them into the tables.
#   bash experiments/render_density_runs.sh DATASET MAP SPACING:VIEWS [SPACING:VIEWS ...]
#   e.g. bash experiments/render_density_runs.sh data/indoor_seed0 mesh 2.0:4 2.0:8 1.0:4 1.0:8
set -euo pipefail
set -o noglob  # the Hydra list override passes through unexpanded
dataset=$1 map=$2
shift 2
for cell in "$@"; do
  spacing=${cell%%:*} views=${cell##*:}
  out=experiments/runs/render_density/$(basename "$dataset")/${map}_s${spacing}_v${views}
  echo "$(date -u +%H:%M:%S) $out (load $(cut -d' ' -f1-3 /proc/loadavg))"
  PYTHONPATH=$PWD OMP_NUM_THREADS=1 CI=true diffloc task=crossmodal "map=$map" \
    "dataset=$dataset" scene=indoor "task.sequences=[query_same,query_reverse]" task.every=4 \
    task.localizer.top_k=20 "task.poses.spacing_m=$spacing" "task.poses.views_per_sample=$views" \
    "task.out_dir=$out" > /dev/null
done
echo "$(date -u +%H:%M:%S) done (load $(cut -d' ' -f1-3 /proc/loadavg))"

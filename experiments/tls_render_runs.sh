#!/usr/bin/env bash
# The TLS render runs of experiments/results/crossmodal_tls_render_indoor_seed{0,1}.md (issue
# 18): one `diffloc task=crossmodal map=tls` run per named render setting on one dataset, every
# 4th frame of query_same and query_reverse (TLS_RENDER_SEQUENCES, comma-separated, replaces
# them, e.g. query_same,query_reverse,changed), the task's defaults otherwise, one thread; then
# the query-by-query breakdown of that run (experiments/crossmodal_breakdown.py, 1 m render
# spacing). Each run writes experiments/runs/tls_render/<dataset name>/<name>/results.json and
# breakdown.{md,json}; experiments/tls_render_table.py turns them into the table.
# TLS_RENDER_ROOT replaces experiments/runs/tls_render (e.g. for diagnostic runs kept apart
# from the ones a rule chooses among). Runs are sequential: the map, database and localisation stages under
# <dataset>/crossmodal/tls/ hold one setting at a time (the render poses are reused).
#   bash experiments/tls_render_runs.sh DATASET NAME 'OVERRIDES' [NAME 'OVERRIDES' ...]
#   e.g. bash experiments/tls_render_runs.sh data/indoor_seed0 default '' multi map.passes=multi
set -euo pipefail
set -o noglob  # the Hydra list override passes through unexpanded
dataset=$1
shift
sequences=${TLS_RENDER_SEQUENCES:-query_same,query_reverse}
breakdown_sequences=()
for sequence in ${sequences//,/ }; do
  breakdown_sequences+=(--sequence "$sequence")
done
while (($# >= 2)); do
  name=$1 overrides=$2
  shift 2
  out=${TLS_RENDER_ROOT:-experiments/runs/tls_render}/$(basename "$dataset")/$name
  echo "$(date -u +%H:%M:%S) $out: $overrides (load $(cut -d' ' -f1-3 /proc/loadavg))"
  cmd="diffloc task=crossmodal map=tls dataset=$dataset scene=indoor"
  cmd+=" task.sequences=[$sequences] task.every=4 task.out_dir=$out $overrides"
  # shellcheck disable=SC2086  # the overrides are separate words
  PYTHONPATH=$PWD OMP_NUM_THREADS=1 CI=true $cmd > /dev/null
  PYTHONPATH=$PWD OMP_NUM_THREADS=1 python3 experiments/crossmodal_breakdown.py \
    --dataset "$dataset" --map tls "${breakdown_sequences[@]}" \
    --spacing-m 1.0 --command "$cmd" --out "$out/breakdown" > /dev/null
done
echo "$(date -u +%H:%M:%S) done (load $(cut -d' ' -f1-3 /proc/loadavg))"

#!/usr/bin/env bash
# Reproduce the structure of seed 1's Tables I-IV on the default indoor scene and the outdoor
# courtyard, and seed 2's Tables I, III, IV and V (crossmodal_tables) on the indoor scene. Each table is a named setup of the `experiment` config group
# (diffloc/conf/experiment/<name>.yaml: its overrides and the sweep's hydra.sweeper.params), run
# as `diffloc -m +experiment=<name>`; this script runs them and post-processes their sweep
# folders (experiments/tables.py, experiments/heldout.py). Each table in experiments/results/
# starts with the command that made it. Scene seed 0 (the tuning seed) first, then the held-out
# seeds (heldout_*.md).
#   bash experiments/run_tables.sh            (hours on 2 cores; every stage is cached)
set -euo pipefail
set -o noglob  # Hydra list overrides such as reloc.sequences=[a,b] pass through unexpanded
runs=experiments/runs
nl=$'\n'
# experiment NAME [OVERRIDE ...]: run `diffloc -m +experiment=NAME ...`; sets cmd.
experiment() {
  cmd="diffloc -m +experiment=$*"
  $cmd
}
table() {  # table SWEEP_DIR KIND OUT "COMMAND" ["NOTE"]
  python3 experiments/tables.py "$1" --kind "$2" --out "experiments/results/$3" --command "$4" \
    --note "${5:-}"
}
# heldout stats|differences NAME "COMMANDS" [OPTION ...] -- DIR ...
# experiments/results/heldout_NAME[_differences].md/.json from the job or sweep folders DIR;
# COMMANDS (one per line) head the report; OPTIONs are passed on (--compare, --note).
heldout() {
  local report=$1 name=$2 commands=$3 line args=()
  shift 3
  while IFS= read -r line; do args+=(--command "$line"); done <<< "$commands"
  while [[ $1 != -- ]]; do args+=("$1"); shift; done
  shift
  python3 experiments/heldout.py "$report" "$@" --name "$name" "${args[@]}"
}

# ------------------------------------------------------------------------------------------------
# Held-out scene seeds (ARCHITECTURE, "Honest evaluation"): everything above is tuned on seed 0;
# the same jobs on other seeds give per-seed values, mean, std and the worst seed
# (heldout_<name>.md), and every claimed ordering (FN >= F >= naive, optimised > raw) a paired
# bootstrap 95 % interval over all held-out queries (heldout_<name>_differences.md): it holds
# only where the interval is above zero.

# heldout_main NAME: the main job of +experiment=heldout_NAME and its held-out statistics; sets
# main_cmd (the command, for the reports of sweeps that reuse its databases).
heldout_main() {
  experiment "heldout_$1"
  main_cmd=$cmd
  heldout stats "$1" "$main_cmd" -- "$runs/heldout_$1"
}

# heldout_ablation NAME: Tables I/II of +experiment=heldout_NAME (the databases of heldout_main),
# statistics and the differences FN - F and F - naive.
heldout_ablation() {
  local cmds
  experiment "heldout_$1"
  cmds="${main_cmd:+$main_cmd$nl}$cmd"
  heldout stats "$1" "$cmds" -- "$runs/heldout_$1"
  heldout differences "$1" "$cmds" --compare reloc.method.points=FN,F \
    --compare reloc.method.points=F,naive -- "$runs/heldout_$1"
}

# heldout_noise EXPERIMENT NAME LEVELS: Table III of +experiment=EXPERIMENT, one sweep per noise
# level of LEVELS ("sigma:priors ..."), e.g. "0.2:0.1,0.2,0.4" puts the pose prior (the user's
# belief of the database pose error) at sigma / 2, sigma and 2 sigma (Hydra cannot pair one
# override with another, so the level is given here); optimised and raw databases; statistics
# and the differences optimised - raw per noise level and prior.
prior_note="db.pose_prior_sigma_m is the user's belief of the database position error; where it \
equals db.noise_sigma the belief is exact, an oracle setting (a user does not know the true \
noise). Half and twice the true noise show the sensitivity to a wrong belief."
heldout_noise() {
  local exp=$1 name=$2 levels=$3 level sigma priors dir cmds="" dirs=()
  for level in $levels; do
    IFS=: read -r sigma priors <<< "$level"
    dir="$runs/heldout_${name}_sigma$sigma"
    experiment "$exp db.noise_sigma=$sigma db.pose_prior_sigma_m=$priors hydra.sweep.dir=$dir"
    cmds+="${cmds:+$nl}$cmd"
    dirs+=("$dir")
  done
  heldout stats "$name" "$cmds" --note "$prior_note" -- "${dirs[@]}"
  heldout differences "$name" "$cmds" --compare task.optimize=true,false --note "$prior_note" \
    -- "${dirs[@]}"
}
all_levels="0:0 0.2:0.1,0.2,0.4 0.4:0.2,0.4,0.8"
oracle_note="ORACLE setting: the pose prior (db.pose_prior_sigma_m, which sizes the builder's \
gates and bounds the optimisation's moves) equals the injected noise db.noise_sigma; a user does \
not know the true noise. The held-out reports (heldout_table3_*.md) also give half and twice it."

# ------------------------------------------------------------------------------------------------
# Seed 2 (localisation in a database rendered from a map, `diffloc task=crossmodal`): Tables I,
# III, IV and V on one dataset, every database a map option of the same task: the rendered TLS
# cloud, lidar cloud and textured lidar mesh, and the mapping images with surfel-map depth
# (map=images), all localised by the same Algorithm 1 on every xm_every-th query frame.
xm_every=4
xm_sequences="[query_same,query_reverse,changed]"
# crossmodal_run DATASET MAP [OVERRIDE ...]: task=crossmodal with MAP on xm_sequences into
# $runs/crossmodal_<dataset>_MAP; sets cmd. Stages are cached under DATASET/crossmodal/ (a
# rerun only scores).
crossmodal_run() {
  local data=$1 map=$2
  shift 2
  cmd="diffloc task=crossmodal map=$map dataset=$data task.sequences=$xm_sequences"
  cmd+=" task.every=$xm_every task.out_dir=$runs/crossmodal_$(basename "$data")_$map $*"
  $cmd
}
# crossmodal_runs DATASET SCENE: task=crossmodal with every map option on DATASET (scene=SCENE),
# and seed 1's hierarchical relocaliser on the same queries, for reference: the results.json of
# a `diffloc task=main` run on DATASET, $seed1_results if set (e.g. outputs/<run>/results.json),
# else this function runs it (its stages are cached too). Sets cmds (the commands, one a line,
# for the tables' headers), runs_args (--run MAP=results.json ...) and seed1.
crossmodal_runs() {
  local data=$1 scene=$2 tag m
  tag=$(basename "$data")
  cmds="" runs_args=()
  for m in tls cloud mesh images hybrid; do
    crossmodal_run "$data" "$m" "scene=$scene"
    cmds+="${cmds:+$nl}$cmd"
    runs_args+=(--run "$m=$runs/crossmodal_${tag}_$m/results.json")
  done
  seed1=${seed1_results:-}
  if [[ -z $seed1 ]]; then
    cmd="diffloc task=main scene=$scene dataset=$data hydra.run.dir=$runs/crossmodal_${tag}_seed1"
    $cmd
    seed1=$runs/crossmodal_${tag}_seed1/results.json
  fi
  cmds+="$nl# seed 1's rows: $seed1"
}
# crossmodal_table SEQUENCE NAME TITLE [OPTION ...]: experiments/results/NAME.md/.json, the
# table of SEQUENCE over the runs of the last crossmodal_runs on $data.
crossmodal_table() {
  local sequence=$1 name=$2 title=$3
  shift 3
  python3 experiments/crossmodal_tables.py --sequence "$sequence" "${runs_args[@]}" \
    --seed1 "$seed1" --dataset "$data" --title "$title" --command "$cmds" \
    --out "experiments/results/$name" "$@"
}

# crossmodal_tables [DATASET]: experiments/results/crossmodal_table{1,3,4,5}_<dataset>.md/.json
# (default data/indoor_seed0).
crossmodal_tables() {
  local data=${1:-data/indoor_seed0} tag
  tag=$(basename "$data")
  crossmodal_runs "$data" indoor
  crossmodal_table query_same "crossmodal_table1_$tag" \
    "Table I (seed 2): same route as the mapping run"
  crossmodal_table query_reverse "crossmodal_table3_$tag" \
    "Table III (seed 2): reverse direction, front-only real images vs 4-view renders" \
    --note "The real-image database holds the mapping run's front camera only; the rendered \
databases have 4 horizontal views per render position. Seed 2's front+side rows need a rig with \
side cameras: crossmodal_front_side (experiments/results/crossmodal_front_side_<dataset>.md)."
  crossmodal_table changed "crossmodal_table4_$tag" "Table IV (seed 2): changed scene"
  python3 experiments/match_quality.py --dataset "$data" --every 8 --tag "$tag" \
    --colored-map "$data/crossmodal/tls/map/colored_map.ply" --name "crossmodal_table5_$tag"
}

# crossmodal_front_side [SEED]: seed 2's Table III "front + side" rows on indoor seed SEED
# (default 0): the scene simulated with a left and a right camera on the mapping run
# (scene.rig.side_camera_yaw_deg=[90,-90] -> sequences mapping_left, mapping_right; every other
# file is that of data/indoor_seed<SEED>), its surfel map, then map=images with the front camera
# only and with front + side (map.sequences=[mapping,mapping_left,mapping_right]) on
# xm_sequences, the validation of task/scene/crossmodal_indoor.yaml as it is:
# experiments/results/crossmodal_front_side_indoor_seed<SEED>.md/.json (one table, a row per
# query sequence and database). Not in crossmodal_tables: it needs its own dataset.
crossmodal_front_side() {
  local seed=${1:-0} data tag cmds xm
  data=data/indoor_seed${seed}_side
  tag=$(basename "$data")
  cmds=""
  for cmd in \
    "diffloc task=simulate scene=indoor scene.seed=$seed scene.rig.side_camera_yaw_deg=[90,-90] \
out_dir=$data" \
    "diffloc task=build_map dataset=$data task.point_maps=[] task.preview_frames=2"; do
    $cmd
    cmds+="${cmds:+$nl}$cmd"
  done
  xm="diffloc task=crossmodal map=images dataset=$data task.sequences=$xm_sequences"
  xm+=" task.every=$xm_every scene=indoor"
  for cmd in \
    "$xm task.out_dir=$runs/crossmodal_${tag}_images" \
    "$xm map.sequences=[mapping,mapping_left,mapping_right] \
task.out_dir=$runs/crossmodal_${tag}_images_front_side"; do
    $cmd
    cmds+="$nl$cmd"
  done
  python3 experiments/crossmodal_tables.py --sequence query_same --sequence query_reverse \
    --sequence changed --run "front=$runs/crossmodal_${tag}_images/results.json" \
    --run "front_side=$runs/crossmodal_${tag}_images_front_side/results.json" \
    --title "Table III (seed 2): real images, front camera vs front + side cameras" \
    --command "$cmds" --out "experiments/results/crossmodal_front_side_indoor_seed$seed" \
    --note "Both databases: every 2nd frame (map.every=2) of the named sequences with \
surfel-map depth, localised by the same Algorithm 1 with the images validation of \
task/scene/crossmodal_indoor.yaml (nothing tuned for the side cameras). The side cameras are \
the front camera turned by +-90 deg about the body's up axis (same intrinsics, same \
timestamps)."
}

# crossmodal_lane [DATASET]: Table I's outdoor row, query_lane of DATASET (default
# data/outdoor_seed0, scene=outdoor: 20 cm cells, 4 m render spacing, 2 m / 30 deg) in the four
# databases: experiments/results/crossmodal_table1_<dataset>.md/.json; seed 1's row as above.
crossmodal_lane() {
  local data=${1:-data/outdoor_seed0} xm_sequences="[query_lane]"
  crossmodal_runs "$data" outdoor
  crossmodal_table query_lane "crossmodal_table1_$(basename "$data")" \
    "Table I (seed 2), outdoors: the parallel lane"
}

# `bash experiments/run_tables.sh FUNCTION ARGS...` runs one of the functions above alone, e.g.
#   bash experiments/run_tables.sh heldout_main main_outdoor
if (($#)); then
  "$@"
  exit
fi

# Tables I/II: ablation over local points (naive / F / FN) and global descriptors, XFeat.
diffloc task=main
experiment table2_ablation_xfeat
table "$runs/ablation_xfeat" ablation table2_ablation_xfeat "$cmd"
table "$runs/ablation_xfeat" runtime table4_runtime_xfeat "$cmd"

# Table II, bottom: ORB features (NetVLAD retrieval).
diffloc task=main features=orb
experiment table2_ablation_orb
table "$runs/ablation_orb" ablation table2_ablation_orb "$cmd"

# Seed 1's own protocol beside diffloc's defaults (same database); one run, no sweep.
cmd="diffloc +experiment=seed1_protocol"
$cmd
{ printf 'Made by:\n\n```bash\n%s\n```\n\n' "$cmd"; cat "$runs/seed1_protocol/results.md"; } \
  > experiments/results/seed1_protocol.md
cp "$runs/seed1_protocol/results.json" experiments/results/seed1_protocol.json

# Table III: database position noise, with and without the surfel optimisation.
experiment table3_noise
table "$runs/noise_epipolar" noise table3_noise "$cmd" "$oracle_note"

# Outdoor courtyard (scene=outdoor): the query sequence `query_lane` and the validation thresholds
# of diffloc/conf/reloc/outdoor.yaml (theta_dist 0.8 m, 6 m/s); recall is still within 0.3 m.
diffloc task=main scene=outdoor
experiment table2_ablation_xfeat_outdoor
table "$runs/ablation_xfeat_outdoor" ablation table2_ablation_xfeat_outdoor "$cmd"
table "$runs/ablation_xfeat_outdoor" runtime table4_runtime_xfeat_outdoor "$cmd"
experiment table3_noise_outdoor
table "$runs/noise_outdoor" noise table3_noise_outdoor "$cmd" "$oracle_note"
experiment table3_noise_outdoor_epipolar
table "$runs/noise_outdoor_epipolar" noise table3_noise_outdoor_epipolar "$cmd" "$oracle_note"

# Seed 2's Tables I, III, IV, V on the default indoor scene, Table III's front + side rows on
# the indoor scene with side cameras (seed 0, then held-out seed 1), Table I's outdoor row
# (every 4th query frame).
crossmodal_tables data/indoor_seed0
crossmodal_front_side 0
crossmodal_front_side 1  # held out: the same settings, run once
crossmodal_lane data/outdoor_seed0

# Indoors: main job and Tables I/II (XFeat, ORB) on seeds 1-5, Table III on seeds 1-3.
heldout_main main
heldout_main main_fresh  # seeds 6-8: run after the track's planarity test was set on seeds 1-5
# Whether the validation's evidence separates the wrong query_reverse poses from right ones.
python3 experiments/validation_evidence.py "$runs/heldout_main" \
  --out experiments/results/validation_evidence_indoor
heldout_ablation ablation_xfeat
heldout_ablation ablation_xfeat_small
heldout_main main_orb
heldout_ablation ablation_orb
# The prior at twice the noise first (the goal: the optimisation raises recall on every held-out
# seed), then equal to the noise (an oracle) and half of it, one report each (committed as they
# finish), then all levels with sigma 0 in one report (it reuses those databases).
heldout_noise heldout_table3_noise_epipolar table3_noise_epipolar_prior2x "0.2:0.4 0.4:0.8"
heldout_noise heldout_table3_noise_epipolar table3_noise_epipolar_prior1x "0.2:0.2 0.4:0.4"
heldout_noise heldout_table3_noise_epipolar table3_noise_epipolar_priorhalf "0.2:0.1 0.4:0.2"
heldout_noise heldout_table3_noise_epipolar table3_noise_epipolar "$all_levels"

# Outdoors: main job and Tables I/II on seeds 1-3, Table III on seeds 1-2.
heldout_main main_outdoor
heldout_main main_outdoor_fresh  # seeds 4-6: run after the track rule was chosen on seeds 1-3
python3 experiments/validation_evidence.py "$runs/heldout_main_outdoor" \
  --out experiments/results/validation_evidence_outdoor
heldout_ablation ablation_xfeat_outdoor
heldout_noise heldout_table3_noise_outdoor table3_noise_outdoor_prior2x "0.2:0.4 0.4:0.8"
heldout_noise heldout_table3_noise_outdoor table3_noise_outdoor_prior1x "0.2:0.2 0.4:0.4"
heldout_noise heldout_table3_noise_outdoor table3_noise_outdoor_priorhalf "0.2:0.1 0.4:0.2"
heldout_noise heldout_table3_noise_outdoor table3_noise_outdoor "$all_levels"

#!/usr/bin/env bash
# The datasets the perception package is trained and benchmarked on (README, "Detection and tracking").
# Each is `transtac-sim generate` of a scene in scenes/perception/; re-running resumes what is missing.
#   bash scripts/make_perception_datasets.sh [train|heldout|fusion|all]     (default all; run from the repo root)
# The contact scenes take a few seconds a frame on a GPU and about half a minute on the 2-core CPU.
# The shipped model was trained on datasets/detector_train_rest (2-core CPU) and datasets/detector_train_contact
# (one H100); the benchmarks read datasets/perception_heldout, track_roll and track_large (one H100), and
# scripts/bench_fusion.py datasets/fusion_distances (contact-free: about a minute a sequence on the 2-core CPU).
set -euo pipefail
cd "$(dirname "$0")/.."
cli=${TRANSTAC_SIM_CLI:-.venv/bin/transtac-sim}
what=${1:-all}
gen() { $cli generate "scenes/perception/$1.toml" --out "datasets/$1" "${@:2}"; }
if [ "$what" = train ] || [ "$what" = all ]; then
  gen detector_train_rest --frames 2
  gen detector_train_contact
fi
if [ "$what" = heldout ] || [ "$what" = all ]; then
  gen perception_heldout
  gen track_roll
  gen track_large
fi
if [ "$what" = fusion ] || [ "$what" = all ]; then
  gen fusion_distances
fi

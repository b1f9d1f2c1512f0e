#!/usr/bin/env bash
# The pair results table at the top of docs/results.md: every method on the held-out frames of
# Nordland, Gardens Point and Corridor, one `fdnet evaluate` per dataset.
#
#   benchmarks/current_results.sh NORDLAND_RUN GARDENS_POINT_RUN OUT_DIR [DATA_DIR]
#
# NORDLAND_RUN: `fdnet train --data DATA/nordland_trimmed --conditions summer,winter --frames 0:1376
#   --validate-reference summer --validate-query winter --validate-frames 1376:1576
#   --validate-tolerance 0 --preset cpu --out NORDLAND_RUN`
# GARDENS_POINT_RUN: `fdnet train --data DATA/gardens_point --conditions day_right,night_right,day_left
#   --frames 0:100 --validate-reference day_left --validate-query night_right --validate-frames 0:100
#   --validate-tolerance 2 --preset cpu --out GARDENS_POINT_RUN`
# Corridor is never trained on: FDNet and the trunk come from the Gardens Point run.
set -euo pipefail
nordland_run=$1 gardens_run=$2 out=$3 data=${4:-../shared/data}
methods=fdnet,trunk,trunk-whitened,sad,hog,gist
mkdir -p "$out"
fdnet evaluate --data "$data/nordland_trimmed" --reference summer --query winter --frames 1576:2576 --tolerance 0 \
    --method $methods --checkpoint "$nordland_run" --fit "$data/nordland_trimmed" --fit-frames 0:1376 \
    --json "$out/nordland.json" --table markdown > "$out/nordland.md"
fdnet evaluate --data "$data/gardens_point" --reference day_right --query night_right --frames 100:200 \
    --method $methods --checkpoint "$gardens_run" --fit "$data/gardens_point" --fit-frames 0:100 \
    --method-set trunk-whitened:dim=256 --json "$out/gardens_point.json" --table markdown > "$out/gardens_point.md"
fdnet evaluate --data "$data/corridor" --dataset-format auto \
    --method $methods --checkpoint "$gardens_run" --fit "$data/gardens_point" --fit-frames 0:100 \
    --method-set trunk-whitened:dim=256 --json "$out/corridor.json" --table markdown > "$out/corridor.md"

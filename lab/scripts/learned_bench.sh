#!/usr/bin/env bash
# The learned-feature rows of lab/notes/BENCHMARKS.md ("Learned features and LightGlue"): `sara bench`
# with the presets aliked-lightglue, disk-lightglue and xfeat-lighterglue.
#
#   lab/scripts/learned_bench.sh JOB
#
# JOB (each one is a plain `sara bench` command, printed before it runs; re-running a JOB resumes:
# finished methods are skipped, matching resumes pair by pair):
#   aliked-headline-fast  ALIKED+LightGlue, bm-moldGoldCape, sara and retrieval
#   aliked-headline       ALIKED+LightGlue, bm-moldGoldCape, exhaustive too (hours on 2 cores)
#   xfeat-small           XFeat+LighterGlue, the five smaller scenes, exhaustive/retrieval/sara
#   xfeat-big-fast        XFeat+LighterGlue, bm-moldGoldCape, sara and retrieval
#   xfeat-big             XFeat+LighterGlue, bm-moldGoldCape, exhaustive too
#   aliked-small          ALIKED+LightGlue, the five smaller scenes, exhaustive/retrieval/sara
#   disk-headline-fast    DISK+LightGlue, bm-moldGoldCape, sara and retrieval
#   disk-headline         DISK+LightGlue, bm-moldGoldCape, exhaustive too
#   disk-small            DISK+LightGlue, the five smaller scenes, exhaustive/retrieval/sara
#   aliked1024-headline   ALIKED+LightGlue with 1,024 keypoints per image (-s extract.max_num_features=1024),
#                         bm-moldGoldCape, exhaustive/retrieval/sara: the complete side-by-side comparison
#                         that 2 CPU cores can finish in about an hour (2,048 keypoints: ~3 s per pair)
#   aliked1024-small      the same 1,024 keypoints, the five smaller scenes, exhaustive/retrieval/sara
#   aliked1024-small-sara SARA alone, as aliked1024-small, into a new folder (after the learned budget changed)
#   disk1024-headline-fast, disk1024-headline, disk1024-small
#                         DISK+LightGlue at 1,024 keypoints, as the three jobs above
#   xfeat-templering      XFeat+LighterGlue, middlebury-templeRing alone, exhaustive/retrieval/sara
#   queue JOB...          run several jobs one after the other (a failed job does not stop the rest)
#
# Environment: METHODS (replaces a job's list of methods), DATA (default ../shared/data relative to the repo), OUT (default bench_learned beside the repo),
# WORKERS (default 2: learned extraction and matching in 2 processes with 1 torch thread each),
# SARA_COMMIT (optional: run the code of this commit, copied once to $OUT/src-<commit>, instead of the
# working tree, so that edits made while a job runs for hours cannot change it halfway).
# Long jobs: nohup lab/scripts/learned_bench.sh aliked-headline > ../bench_learned/aliked-headline.log 2>&1 &
set -euo pipefail

here="$(cd "$(dirname "$0")/../.." && pwd)"
DATA="${DATA:-$(cd "$here/../shared/data" && pwd)}"
OUT="${OUT:-$here/../bench_learned}"
WORKERS="${WORKERS:-2}"
PYTHON="${PYTHON:-$here/.venv/bin/python}"
if [ -n "${SARA_COMMIT:-}" ]; then
    src="$OUT/src-$SARA_COMMIT"
    if [ ! -d "$src/src/sara" ]; then
        mkdir -p "$src" && git -C "$here" archive "$SARA_COMMIT" src | tar -x -C "$src"
    fi
    export PYTHONPATH="$src/src${PYTHONPATH:+:$PYTHONPATH}"
fi
SARA=("$PYTHON" -m sara)
EXTRA=()  # more -s KEY=VALUE for one job

big="$DATA/bm-moldGoldCape"
small=("$DATA/strecha-fountain-P11" "$DATA/middlebury-templeSparseRing" "$DATA/strecha-Herz-Jesus-P25"
       "$DATA/strecha-castle-P30" "$DATA/middlebury-templeRing")

bench() {  # bench PRESET OUTNAME METHODS CHUNK SCENE...
    # CHUNK: pairs per matcher job (match.chunk_size). The default 128 leaves one of the two workers
    # idle on a method with fewer than 129 pairs (SARA on the small scenes), so the small scenes use 8.
    local preset="$1" name="$2" methods="${METHODS:-$3}" chunk="$4"
    shift 4
    local cmd=("${SARA[@]}" bench "$@" --preset "$preset" --methods "$methods" -s "execute.workers=$WORKERS"
               "${EXTRA[@]}")
    [ "$chunk" = default ] || cmd+=(-s "match.chunk_size=$chunk")
    cmd+=(--out "$OUT/$name" --no-plot -q)
    echo "[$(date -Is)] ${PYTHONPATH:+PYTHONPATH=$PYTHONPATH }${cmd[*]}"
    "${cmd[@]}"
    echo "[$(date -Is)] done: $OUT/$name/results.md"
}

case "${1:-}" in
    aliked-headline-fast) bench aliked-lightglue aliked-lightglue-big sara,retrieval default "$big" ;;
    aliked-headline)      bench aliked-lightglue aliked-lightglue-big exhaustive,retrieval,sara default "$big" ;;
    xfeat-small)          bench xfeat-lighterglue xfeat-lighterglue-small exhaustive,retrieval,sara 8 "${small[@]}" ;;
    xfeat-big-fast)       bench xfeat-lighterglue xfeat-lighterglue-big sara,retrieval default "$big" ;;
    xfeat-big)            bench xfeat-lighterglue xfeat-lighterglue-big exhaustive,retrieval,sara default "$big" ;;
    aliked-small)         bench aliked-lightglue aliked-lightglue-small exhaustive,retrieval,sara 8 "${small[@]}" ;;
    disk-headline-fast)   bench disk-lightglue disk-lightglue-big sara,retrieval default "$big" ;;
    disk-headline)        bench disk-lightglue disk-lightglue-big exhaustive,retrieval,sara default "$big" ;;
    disk-small)           bench disk-lightglue disk-lightglue-small exhaustive,retrieval,sara 8 "${small[@]}" ;;
    aliked1024-headline)  EXTRA=(-s extract.max_num_features=1024)
                          bench aliked-lightglue aliked1024-lightglue-big sara,retrieval,exhaustive default "$big" ;;
    aliked1024-small)     EXTRA=(-s extract.max_num_features=1024)
                          bench aliked-lightglue aliked1024-lightglue-small exhaustive,retrieval,sara 8 "${small[@]}" ;;
    aliked1024-small-sara) EXTRA=(-s extract.max_num_features=1024)  # SARA again (a later budget), new folder
                          bench aliked-lightglue aliked1024-lightglue-small-v2 sara 8 "${small[@]}" ;;
    disk1024-headline-fast) EXTRA=(-s extract.max_num_features=1024)
                          bench disk-lightglue disk1024-lightglue-big sara,retrieval default "$big" ;;
    disk1024-headline)    EXTRA=(-s extract.max_num_features=1024)
                          bench disk-lightglue disk1024-lightglue-big sara,retrieval,exhaustive default "$big" ;;
    disk1024-small)       EXTRA=(-s extract.max_num_features=1024)
                          bench disk-lightglue disk1024-lightglue-small exhaustive,retrieval,sara 8 "${small[@]}" ;;
    xfeat-templering)     bench xfeat-lighterglue xfeat-lighterglue-templering exhaustive,retrieval,sara 8 \
                              "$DATA/middlebury-templeRing" ;;
    queue)                shift
                          for job in "$@"; do "$0" "$job" || echo "[$(date -Is)] job $job failed"; done ;;
    *) sed -n '2,29p' "$0"; exit 2 ;;
esac


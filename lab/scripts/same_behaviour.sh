#!/usr/bin/env bash
# Behaviour kept across a refactoring: the same bench (exhaustive and sara, SIFT defaults) on the
# six shared scenes with two source trees, e.g. the commit before the change (a `git worktree`)
# and after it. Features are extracted once (by the first run) and shared by hard links; run the
# three one after the other (a copy taken while old1 still extracts would be incomplete).
#
#   lab/scripts/same_behaviour.sh OLD_SRC NEW_SRC DATA OUT
#
# writes OUT/old1, OUT/old2 (the old code's own run-to-run spread) and OUT/new1; then
#   python lab/scripts/same_behaviour.py OUT old1 old2 new1
# prints pairs.txt digests, registration and AUC@1 / AUC@5 side by side.
set -u
OLD_SRC=$1; NEW_SRC=$2; DATA=$3; OUT=$4
PY=${PYTHON:-python}
SCENES=${SCENES:-"strecha-fountain-P11 middlebury-templeSparseRing strecha-Herz-Jesus-P25 strecha-castle-P30 middlebury-templeRing bm-moldGoldCape"}
for tag in old1 old2 new1; do
  case $tag in old*) src=$OLD_SRC;; *) src=$NEW_SRC;; esac
  for s in $SCENES; do
    if [ ! -d "$OUT/$tag/$s/features" ] && [ -d "$OUT/old1/$s/features" ]; then
      # hard links, but not the lock file: a shared inode would share old1's lock too
      mkdir -p "$OUT/$tag/$s" && cp -al "$OUT/old1/$s/features" "$OUT/$tag/$s/features"
      rm -f "$OUT/$tag/$s/features/.sara.lock"
    fi
    echo "== $tag $s $(date +%T)"
    PYTHONPATH=$src $PY -m sara bench "$DATA/$s" --quiet --out "$OUT/$tag" --methods exhaustive,sara --no-plot \
      > "$OUT/$tag/$s.log" 2>&1 || echo "failed: see $OUT/$tag/$s.log"
  done
done

#!/usr/bin/env bash
# Bilateral integration beside BiNI's own code (xucao-42/bilateral_normal_integration, its CLI with
# its defaults: k 2, 150 iterations, tol 1e-4) on the shared DiLiGenT integration objects,
# interleaved run by run so that machine load hits both alike. Prints one line per run: object,
# program, whole-process seconds, solver seconds (BiNI's `wall_time`; ours from the integrate
# message) and, for BiNI, its reweighting steps. Medians are left to the reader
# (docs/integration.md quotes medians of 3).
#
# Usage, from the project root after `cargo build --release`:
#   benches/bini_side_by_side.sh BINI_DIR PYTHON [REPEATS [DATA_DIR]]
# BINI_DIR: a checkout of BiNI; PYTHON: an interpreter with numba, scipy, opencv and tqdm.
# DATA_DIR: folders of normal_map.png, mask.png and K.txt, by default the shared objects;
# BiNI's own data/Fig7_diligent holds all nine DiLiGenT objects (for timings: five of them are
# held out of development). PHOTOSTEREO: the binary to time (another build, side by side).
set -eu
BINI=${1:?BiNI checkout}; PY=${2:?python with numba}; R=${3:-3}
BIN=${PHOTOSTEREO:-target/release/photostereo}
D=$(cd "${4:-$(dirname "$0")/../../shared/data/integration}" && pwd)
T=$(mktemp -d); trap 'rm -rf "$T"' EXIT
secs() { python3 -c "import sys; print(round(float(sys.argv[2]) - float(sys.argv[1]), 3))" "$@"; }
for d in "$D"/*/; do
  n=$(basename "$d"); [ -f "$d/normal_map.png" ] || continue
  mkdir -p "$T/in/$n"; cp "$d"/{normal_map.png,mask.png,K.txt} "$T/in/$n/"
  for _ in $(seq "$R"); do
    s=$(date +%s.%N)
    j=$(cd "$BINI" && "$PY" cli.py run "$T/in/$n" --output-dir "$T/bini/$n" --json 2>/dev/null)
    e=$(date +%s.%N)
    echo "$n bini $(secs "$s" "$e") $(echo "$j" | python3 -c "import json,sys; d=json.load(sys.stdin)['stats']; print(d['wall_time'], d['iterations'])")"
    for m in bilateral auto; do
      s=$(date +%s.%N)
      "$BIN" integrate --normals "$d/normal_map.png" --mask "$d/mask.png" --camera "$d/K.txt" --method "$m" -o "$T/$n-$m.exr" --force >"$T/log" 2>&1
      e=$(date +%s.%N)
      echo "$n $m $(secs "$s" "$e") $(grep -o 'in [0-9.]* s' "$T/log" | head -1 | cut -d' ' -f2)"
    done
  done
done

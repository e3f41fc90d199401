#!/usr/bin/env bash
# `make demo`: the whole pipeline on the real data bundled in data/ (see data/README.md).
set -euo pipefail
OUT="${1:-demo-output}"
ESMM="${ESMM:-.venv/bin/esmm}"
# The demo owns its output folder: a folder it wrote before (its marker inside) is replaced whole, so that
# a second `make demo` does not stop at the first stage's refusal to write beside an earlier fit; any other
# non-empty folder is left alone.
if [ -e "$OUT" ] && [ -n "$(ls -A "$OUT" 2>/dev/null)" ]; then
    if [ -f "$OUT/.esmm-demo" ]; then
        rm -rf -- "$OUT"
    else
        echo "demo: $OUT exists and was not written by this demo; remove it, or give another folder: make demo DEMO_OUT=dir" >&2
        exit 2
    fi
fi
mkdir -p "$OUT"
echo "written by scripts/demo.sh (make demo); the next run replaces this folder" > "$OUT/.esmm-demo"
say() { printf '\n== %s\n' "$*"; }

say "1/9 calibrate: Arruda-Boyce on Treloar's rubber (published: C_R ~ 0.27 MPa, N ~ 26)"
"$ESMM" calibrate data/tensile/treloar1944/uniaxial.csv --model arruda-boyce \
    --out "$OUT/treloar" --json "$OUT/treloar/treloar.json"

say "2/9 calibrate: the ESEDF on human brain cortex (Budday 2017), tension-compression + shear"
"$ESMM" calibrate data/tensile/budday2017_brain/cortex_tension_compression.csv \
    data/tensile/budday2017_brain/cortex_simple_shear.csv --model esedf --out "$OUT/brain-cortex"

say "3/9 calibrate, batch: every brain region on its own, in parallel"
"$ESMM" calibrate --by specimen data/tensile/budday2017_brain/*.csv --model esedf --out "$OUT/brain-batch"

say "4/9 close the loop: what the hyperelastic model misses in raw VHB 4910 exports (fit on 0.05 /s + relaxation)"
"$ESMM" calibrate data/tensile/vhb4910_raw/lu_0d05_*.csv data/tensile/vhb4910_raw/relax_2d0.csv \
    --discover --out "$OUT/vhb-discover" --json "$OUT/vhb-discover/discover-summary.json"
say "    ... and predict the 0.01 /s tests it never saw (the material is not refitted)"
"$ESMM" evaluate "$OUT/vhb-discover" data/tensile/vhb4910_raw/lu_0d01_*.csv --json "$OUT/vhb-discover/evaluate-0d01.json"

say "5/9 close the loop on raw Instron exports of rat-tail tendon (geometry read from the files' headers): the relaxation"
"$ESMM" calibrate data/tensile/tendon_instron/relax_incubated_1.csv --discover --out "$OUT/tendon-discover"

say "6/9 close the loop on racing-shoe foam, 4 specimens cycled: Mullins, hysteresis, cyclic softening"
"$ESMM" calibrate data/tensile/foam_cyclic/new-heel-tension-?_1.csv --discover --out "$OUT/foam-discover"

say "7/9 prepare: an InVesalius-style liver surface (TotalSegmentator liver, 3 mm) -> tetra spring network"
"$ESMM" prepare data/meshes/ts_liver_3mm_closed.stl --config paper -o "$OUT/liver.h5"
"$ESMM" info "$OUT/liver.h5"

say "8/9 validate: the network (with its volume term) against a felupe continuum, a 20 mm cube in tension, compression, shear"
"$ESMM" validate --specimen --size 4 --out "$OUT/validate-specimen" --json "$OUT/validate-specimen/validate.json"

say "9/9 simulate: the liver under gravity and a scripted grasper, implicit (backward Euler at the frame step, grasper force at 1 kHz), rendered off-screen"
"$ESMM" simulate "$OUT/liver.h5" --scene interactive --video "$OUT/liver.mp4" --out "$OUT/liver-sim"
RTF=$(python3 - "$OUT/liver-sim/summary.json" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
print("%s integrator, %d steps, real-time factor %.3g (simulated %g s in %.3g s of stepping)"
      % (s["method"], s["steps"], s["real_time_factor"] or 0.0, s["simulated_s"], s["stepping_wall_s"]))
PY
)
echo "simulation: $RTF"

say "done; outputs in $OUT/"
ls -1 "$OUT"
cat <<MSG

  calibration reports : $OUT/treloar/report.md, $OUT/brain-cortex/report.md, $OUT/brain-batch/summary.csv
  closing the loop    : $OUT/vhb-discover/discover.md (effects found, error before/after), evaluate-0d01.json,
                        $OUT/tendon-discover/discover.md, $OUT/foam-discover/discover.md
  network vs continuum: $OUT/validate-specimen/ (per-case errors, volume change, plots, XDMF error fields)
  liver asset         : $OUT/liver.h5 (+ liver.xdmf for ParaView)
  video               : $OUT/liver.mp4
  simulation outputs  : $OUT/liver-sim/ (displacement history .h5/.xdmf, grasper force plot)
  simulation speed    : $RTF
MSG

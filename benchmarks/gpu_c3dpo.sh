#!/usr/bin/env bash
# C3DPO's rows of Table 1 (GT-ortho, GT-persp, SH) trained on one GPU as CUDA graphs, in one fixed time budget.
#
#   bash benchmarks/gpu_c3dpo.sh DATA_ROOT OUT_DIR [TRAIN_SECONDS]
#
# DATA_ROOT holds h36m/ (as --root of benchmarks.table1). TRAIN_SECONDS (default 470) is the training time the
# schedule must fit in. The script
#   1. times a C3DPO training iteration (batch 1024) alone at PRECISION, launched op by op and replayed as a CUDA
#      graph (benchmarks.studies.speed_c3dpo);
#   2. at PRECISION (default fp32, the authors'), as CUDA graphs (op by op where a capture fails), takes the
#      inputs of INPUTS (default "gt-ortho gt-persp sh", in that order) whose trainings fit the authors' 109,800
#      iterations into TRAIN_SECONDS side by side (their GPU time adds up), at least the first; where that one
#      alone does not fit, as many iterations as do (the lr drops move with the schedule, as --c3dpo-iterations);
#   3. trains and evaluates C3DPO on those inputs at once (benchmarks.table1 --methods C3DPO --c3dpo-monitor),
#      while a collector copies the test error along training from the checkpoints into OUT_DIR/summary.json,
#      so that a run cut short still reports where it got to.
# ITERATIONS fixes the schedule instead (every input of INPUTS; the lr drops at 2/3 and 8/9 of it): a run cut short
# by the budget resumes from its last checkpoint when the script runs again on the same machine, same settings.
# COMPILE=1 also compiles the iteration with torch.compile (timed in step 1 as well; the schedule follows its time).
# REPEAT=8 uses each minibatch for 8 iterations, as the authors' data loader did (baselines.c3dpo; default 1).
# LR sets the learning rate (default: benchmarks.table1's, chosen on a held-out training subject; 1e-3: the authors').
# DEVICE (default cuda) names the torch device. OUT_DIR gets one log per input, the timings (speed_c3dpo.json) and
# summary.json (the chosen schedule, each input's table row, its own-protocol numbers and the monitored curve);
# the script's own output says how far each training got every 30 s.
set -u
root=${1:?DATA_ROOT}
out=${2:?OUT_DIR}
budget=${3:-470}
precision=${PRECISION:-fp32}
work=${TMPDIR:-/tmp}/gpu_c3dpo
mkdir -p "$out" "$work"
source "$(dirname "$0")/gpu_common.sh"

speed() {
  "$py" -m benchmarks.studies.speed_c3dpo --batch 1024 --repeats 40 --warmup 5 --device "${DEVICE:-cuda}" \
    --precision "$precision" --out "$work/speed" "$@"
}
eager=""
compile=""
if [ "${COMPILE:-0}" = 1 ]; then
  speed --compile && compile=--compile || echo "torch.compile failed: CUDA graphs alone" >&2
fi
if [ -z "$compile" ] && ! speed; then
  echo "CUDA graphs failed: training op by op" >&2
  eager=--c3dpo-eager
  speed --eager-only || exit 1
fi
cp "$work/speed/speed_c3dpo.json" "$out/"

read -r iterations chosen use_compile < <("$py" - "$work" "$budget" "$precision" ${INPUTS:-gt-ortho gt-persp sh} <<'EOF'
import json, os, sys
from pathlib import Path
from baselines.c3dpo import PAPER_ITERATIONS
work, budget, precision, inputs = Path(sys.argv[1]), float(sys.argv[2]), sys.argv[3], sys.argv[4:]
rows = json.loads((work / "speed" / "speed_c3dpo.json").read_text())["results"]
t = min(r["iteration_s"] for r in rows if r["precision"] == precision)  # the fastest way that ran
compiled = any(r["compile"] and r["iteration_s"] == t for r in rows)  # compile only where that is faster
# 0.85: room for the monitor's evaluations and the data loading, which the timing leaves out
n = max(1, min(len(inputs), int(0.85 * budget / (PAPER_ITERATIONS * t))))
iterations = max(100, min(PAPER_ITERATIONS, int(0.85 * budget / (n * t)) // 100 * 100))
if os.environ.get("ITERATIONS"):  # a fixed schedule: every input of INPUTS, resumed from its checkpoint if any
    n, iterations = len(inputs), int(os.environ["ITERATIONS"])
json.dump({"budget_s": budget, "iteration_s_alone": t, "precision": precision, "inputs": inputs[:n],
           "iterations": iterations, "paper_iterations": PAPER_ITERATIONS, "compile": compiled},
          open(work / "schedule.json", "w"), indent=2)
print(iterations, ",".join(inputs[:n]), int(compiled))
EOF
)
[ -n "${chosen:-}" ] || exit 1
[ "${use_compile:-0}" = 1 ] || compile=""
echo "schedule: $iterations iterations, $precision trunks, inputs $chosen${compile:+, compiled}"

collect() {
  "$py" - "$work" "$out/summary.json" <<'EOF'
import json, sys
from pathlib import Path
from benchmarks.common import checkpoint_progress, write_json
work, dest = Path(sys.argv[1]), Path(sys.argv[2])
summary = {"schedule": json.loads((work / "schedule.json").read_text())}
for inp in summary["schedule"]["inputs"]:
    run = work / f"run-{inp}"
    entry = checkpoint_progress(run)
    if (run / "table1.json").exists():
        entry["table1"] = json.loads((run / "table1.json").read_text())
    summary[inp] = entry
def progress(k, v):
    last = f", test {v['monitor'][-1]['test_mpjpe_mm']:.1f} mm" if v.get("monitor") else ""
    return f"{k}: {v.get('iteration', 0)} it{last}"
print("  ".join(progress(k, v) for k, v in summary.items() if k != "schedule"))
write_json(dest, summary)
EOF
}

left=$((budget + 75 - ($(date +%s) - t_start)))  # 75 s beyond the training for loading and the final evaluation
for inp in ${chosen//,/ }; do
  timeout "$left" "$py" -m benchmarks.table1 --root "$root" --input "$inp" --methods C3DPO \
    --c3dpo-iterations "$iterations" --c3dpo-precision "$precision" --c3dpo-repeat "${REPEAT:-1}" --c3dpo-monitor \
    ${LR:+--c3dpo-lr "$LR"} $eager ${compile:+--c3dpo-compile} \
    --device "${DEVICE:-cuda}" --no-progress --out "$work/run-$inp" > "$out/$inp.log" 2>&1 &
done
watch_jobs
for inp in ${chosen//,/ }; do echo "== $inp"; tail -n 6 "$out/$inp.log"; done
echo "total $(( $(date +%s) - t_start )) s"

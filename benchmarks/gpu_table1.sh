#!/usr/bin/env bash
# Rows of Table 1 trained side by side on one GPU, each in its own process, within one time budget.
#
#   bash benchmarks/gpu_table1.sh DATA_ROOT OUT_DIR SECONDS ITERATIONS INPUT:ROW [INPUT:ROW ...]
#
# DATA_ROOT holds h36m/ (as --root of benchmarks.table1); ITERATIONS is --iterations of benchmarks.table1 (the
# paper's schedule is 70000); each INPUT:ROW (for example "gt-ortho:GT 3D") is one benchmarks.table1 run with
# --input INPUT --methods ROW. The runs share one pseudo-label cache and split the CPU cores between their label
# solves. A run still going after SECONDS is stopped; a collector reads every run's table row, or, for one cut
# short, the iteration its last checkpoint reached, into OUT_DIR/summary.json every 30 s, so that a run cut short
# still reports where it got to. OUT_DIR also gets each run's log and table1.md. DEVICE (default cuda) names the
# torch device; JOBS (default: the cores divided by the runs) the label solves each run may start.
set -u
root=${1:?DATA_ROOT}
out=${2:?OUT_DIR}
budget=${3:?SECONDS}
iterations=${4:?ITERATIONS}
shift 4
[ $# -ge 1 ] || { echo "expected at least one INPUT:ROW, for example 'gt-ortho:GT 3D'" >&2; exit 2; }
work=${TMPDIR:-/tmp}/gpu_table1
mkdir -p "$out" "$work"
source "$(dirname "$0")/gpu_common.sh"

jobs_each=${JOBS:-$(( $(nproc) / $# ))}
[ "$jobs_each" -ge 1 ] || jobs_each=1
i=0
for spec in "$@"; do
  inp=${spec%%:*}
  row=${spec#*:}
  i=$((i + 1))
  echo "run $i: $row on $inp"
  printf '%s\t%s\n' "$inp" "$row" > "$work/run$i.spec"
  timeout "$budget" "$py" -m benchmarks.table1 --root "$root" --input "$inp" --methods "$row" \
    --iterations "$iterations" --device "${DEVICE:-cuda}" --jobs "$jobs_each" --no-progress \
    --labels-dir "$work/labels" --out "$work/run$i" > "$out/run$i.log" 2>&1 &
done

collect() {
  "$py" - "$work" "$out/summary.json" "$iterations" <<'EOF'
import json, sys
from pathlib import Path
from benchmarks.common import checkpoint_progress, write_json
work, dest, iterations = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])
summary = {"iterations": iterations, "runs": []}
for spec in sorted(work.glob("run*.spec"), key=lambda p: int(p.stem[3:])):
    inp, row = spec.read_text().rstrip("\n").split("\t")
    run = work / spec.stem
    entry = {"run": spec.stem, "input": inp, "row": row, **checkpoint_progress(run)}
    if (run / "table1.json").exists():
        entry["table1"] = json.loads((run / "table1.json").read_text())
    summary["runs"].append(entry)
def progress(e):
    return f"{e['row']} ({e['input']}): " + ("done" if "table1" in e else f"{e.get('iteration', 0)} it")
print("; ".join(progress(e) for e in summary["runs"]))
write_json(dest, summary)
EOF
}

watch_jobs
for spec in "$work"/run*.spec; do
  run=${spec%.spec}
  n=$(basename "$run")
  [ -f "$run/table1.md" ] && cp "$run/table1.md" "$out/$n-table1.md"
  echo "== $n: $(tr '\t' ' ' < "$spec")"
  tail -n 4 "$out/$n.log"
done
echo "total $(( $(date +%s) - t_start )) s"

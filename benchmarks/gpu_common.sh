# Sourced by the benchmarks/gpu_*.sh scripts (run from the repository root): one thread per process, the Python to
# use ($py), the start time ($t_start), and a check that torch and the data libraries import and see the GPU.
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1 PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
py=$(command -v python3 || command -v python)
t_start=$(date +%s)

nvidia-smi -L 2>/dev/null
"$py" -c "import torch, numpy, scipy, sklearn, h5py; print('torch', torch.__version__, 'numpy', numpy.__version__,
          'gpu', torch.cuda.is_available() and torch.cuda.get_device_name(0))" || exit 1

# Every 30 s until the background jobs end, the seconds since the start and what the caller's `collect` prints;
# then `collect` once more.
watch_jobs() {
  while [ -n "$(jobs -rp)" ]; do
    sleep 30
    echo "$(( $(date +%s) - t_start )) s: $(collect)"
  done
  wait
  collect
}

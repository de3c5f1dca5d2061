#!/bin/bash
# The diagnosis grid (bench_diagnosis_grid.py run) on a lent machine's CPU cores, one process per scenario
# and draw.  Run from the repository root with data/grid (bench_diagnosis_grid.py make) and data/devdeps
# (tqdm) carried: PROCS=16 RUN_S=570 timeout 590 bash benchmarks/device_grid.sh
set -u
export PYTHONPATH=$PWD:$PWD/data/devdeps
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
mkdir -p "$OUT/grid"
cp data/grid/*.npz "$OUT/grid/"
nproc; python -c "import torch, numpy; print(torch.__version__, numpy.__version__)"; lscpu | grep "Model name"
# longest first (the pair and the defocus), so that the last wave is short
{
for d in 0 1 2; do echo "chamber_z+15&thermal_bump_m1_400 $d"; done
for s in chamber_z+12 chamber_z-20 chamber_z+25 source_divergence+0.5 source_divergence-0.3 thermal_bump_m1_300 thermal_bump_m1_450 detector_blur_0.03 detector_blur_0.06 none; do
  for d in 0 1 2; do echo "$s $d"; done
done
} | xargs -P "${PROCS:-15}" -L 1 bash -c 'timeout ${RUN_S:-560} python benchmarks/bench_diagnosis_grid.py run "$OUT/grid" --only "$0" --draw "$1" --check torch --threads 1 > "$OUT/grid/log_${0}_$1.txt" 2>&1; echo "done $0 $1 rc=$?"'
python benchmarks/bench_diagnosis_grid.py table "$OUT/grid" > "$OUT/table.md" 2>&1
cat "$OUT/table.md"
# the results come back as one archive: files whose names hold + and & do not come back one by one
# (added after the run in docs/benchmarks.md, whose files did not come back)
tar -C "$OUT" -czf "$OUT/grid.tgz" --exclude="*.npz" grid && rm -rf "$OUT/grid"

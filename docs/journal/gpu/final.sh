#!/bin/bash
# After the sync-free cumulative product: the capture of the hold assignment, the DIDER job step graphed and eager,
# and the CUDA tests.
source docs/journal/gpu/setup.sh
timeout 40 python3 docs/journal/gpu/capture_diag.py dider hold 2>&1 | grep RESULT | tee "$OUT/diag.jsonl"
timeout 40 python3 docs/journal/gpu/capture_diag.py dider full 2>&1 | grep RESULT | tee -a "$OUT/diag.jsonl"
echo "diag at $(( $(date +%s) - start )) s"
timeout 75 python3 -m dider.bench --device cuda --only 'job/dider/synth/b016' --out "$OUT/bench_gpu.json" \
  > "$OUT/bench.log" 2>&1; echo "bench rc $? at $(( $(date +%s) - start )) s"; grep -E "^job/" "$OUT/bench.log"
timeout 60 python3 -m pytest -q -p no:cacheprovider tests/test_gpu.py -m gpu > "$OUT/tests.log" 2>&1
echo "tests rc $? at $(( $(date +%s) - start )) s"; grep -E "passed|failed|^FAILED" "$OUT/tests.log" | tail -8

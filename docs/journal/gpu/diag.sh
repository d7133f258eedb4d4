#!/bin/bash
# Capture diagnosis on a lent GPU (capture_diag.py: each stage in its own process, the first group at once, the
# second one by one for its timings), then the CUDA tests and a real DNRI job.
source docs/journal/gpu/setup.sh
mkdir -p /tmp/diag
run() { timeout 60 python3 docs/journal/gpu/capture_diag.py "$@" > "/tmp/diag/$1_$2_${3:-}.log" 2>&1; grep RESULT "/tmp/diag/$1_$2_${3:-}.log" | tee -a "$OUT/diag.jsonl"; }
run dider sync & run dider hold & run dider segment & run dider encoder & run dider forward & run dider recover & run dider_skid segment & run dider_paper segment & wait
echo "group 1 at $(( $(date +%s) - start )) s"
for m in dnri dider; do run $m full; done; run dider full loop
for m in dider_skid dider_paper dider_gate nri; do run $m full; done
tar czf "$OUT/diag_logs.tgz" -C /tmp diag
echo "group 2 at $(( $(date +%s) - start )) s"
timeout 120 python3 -m pytest -q -p no:cacheprovider tests/test_gpu.py -m gpu > "$OUT/tests.log" 2>&1
echo "tests rc $? at $(( $(date +%s) - start )) s"; grep -E "passed|failed|^FAILED" "$OUT/tests.log" | tail -8
timeout 70 python3 -m dider.run model=dnri trainer=gpu trainer.max_epochs=1 trainer.limit_train_batches=300 \
  logger=csv "~callbacks.timelines" "+callbacks.step_timer._target_=step_timer.StepTimer" \
  "+callbacks.step_timer.path=$OUT/job_dnri.json" hydra.run.dir=/tmp/job_dnri > "$OUT/job_dnri.log" 2>&1
echo "job dnri rc $? at $(( $(date +%s) - start )) s: $(cat $OUT/job_dnri.json 2>/dev/null | tr -d '\n ')"
grep -E "Error|captured" "$OUT/job_dnri.log" | head -3

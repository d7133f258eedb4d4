#!/bin/bash
# The GPU checks of the graphed training step in one call of a lent GPU machine (about 7 minutes; run from the
# repository root with hydra-core, omegaconf and antlr4 as wheels in .whl/, carry=[".whl"]): the CUDA tests; each
# model's bare step captured and replayed against eager (capture_diag.py); the real-job step benchmark of DNRI, DIDER
# and DIDER (SKID) at batch 16 and 128, graphed and eager (cuda_graph=false) in the same process; and the first 300
# steps of paper-sized DNRI and DIDER jobs (python -m dider.run, deterministic) with their validation and test.
# Writes under $OUT: tests.log, diag.jsonl, bench_gpu.json, bench.log, job_<model>.json.
source docs/journal/gpu/setup.sh
nvidia-smi -L; python3 -c "import torch, lightning; print(torch.__version__, lightning.__version__, torch.cuda.get_device_name(0))"
timeout 120 python3 -m pytest -q -p no:cacheprovider tests/test_gpu.py -m gpu > "$OUT/tests.log" 2>&1
echo "tests rc $? at $(( $(date +%s) - start )) s"; grep -E "passed|failed|^FAILED" "$OUT/tests.log" | tail -8
for m in dnri dider dider_skid dider_paper dider_gate nri; do
  timeout 40 python3 docs/journal/gpu/capture_diag.py $m full 2>&1 | grep RESULT | tee -a "$OUT/diag.jsonl"
done
echo "diag at $(( $(date +%s) - start )) s"
timeout 280 python3 -m dider.bench --device cuda --only 'job/(dnri|dider|dider_skid)/synth/b(016|128)' \
  --out "$OUT/bench_gpu.json" > "$OUT/bench.log" 2>&1; echo "bench rc $? at $(( $(date +%s) - start )) s"
grep -E "^job/" "$OUT/bench.log"
for model in dnri dider; do
  timeout 70 python3 -m dider.run model=$model trainer=gpu trainer.max_epochs=1 trainer.limit_train_batches=300 \
    logger=csv "~callbacks.timelines" "+callbacks.step_timer._target_=step_timer.StepTimer" \
    "+callbacks.step_timer.path=$OUT/job_$model.json" hydra.run.dir=/tmp/job_$model > "/tmp/job_$model.log" 2>&1
  echo "job $model rc $? at $(( $(date +%s) - start )) s: $(tr -d '\n ' < "$OUT/job_$model.json" 2>/dev/null)"
  grep -E "Error|captured" "/tmp/job_$model.log" | head -3
done

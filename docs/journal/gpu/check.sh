#!/bin/bash
# The GPU checks of the graphed training step, in one call of a lent GPU machine (run from the repository root, with
# hydra-core, omegaconf and antlr4 as wheels in .whl/): the CUDA tests, the real-job step benchmark of each model at
# batch 16 and 128 graphed and eager (cuda_graph=false: the loop as it was) in the same process, and the first 300
# steps of paper-sized DNRI and DIDER jobs (python -m dider.run, deterministic) with their validation and test.
# Writes under $OUT: tests.log, bench_gpu.json, job_<model>.json, *.log.
source docs/journal/gpu/setup.sh
nvidia-smi -L; python3 -c "import torch, lightning; print(torch.__version__, lightning.__version__, torch.cuda.get_device_name(0))"
timeout 150 python3 -m pytest -q -x -p no:cacheprovider tests/test_gpu.py tests/test_precision.py \
  -m gpu > "$OUT/tests.log" 2>&1; echo "tests rc $? in $(( $(date +%s) - start )) s"; tail -3 "$OUT/tests.log"
timeout 200 python3 -m dider.bench --device cuda --only 'job/(dnri|dider)/synth/b(016|128)' \
  --out "$OUT/bench_gpu.json" > "$OUT/bench.log" 2>&1; echo "bench rc $? at $(( $(date +%s) - start )) s"
grep -E "^job/" "$OUT/bench.log"
for model in dnri dider; do
  timeout 80 python3 -m dider.run model=$model trainer=gpu trainer.max_epochs=1 trainer.limit_train_batches=300 \
    logger=csv "~callbacks.timelines" "+callbacks.step_timer._target_=step_timer.StepTimer" \
    "+callbacks.step_timer.path=$OUT/job_$model.json" hydra.run.dir=/tmp/job_$model > "$OUT/job_$model.log" 2>&1
  echo "job $model rc $? at $(( $(date +%s) - start )) s: $(cat $OUT/job_$model.json 2>/dev/null | tr -d '\n ')"
  grep -iE "captured|could not be captured|Error" "$OUT/job_$model.log" | head -3
done

#!/bin/bash
# The synthetic standard protocol (experiment=synth_protocol: 10k clips x 16 epochs at batch 32, fp32) for several
# models and seeds at once on one lent GPU, every job its own process, each graphed (cuda_graph=auto). Not yet measured
# on the chip: its one call ran every job on the machine's CPUs (trainer=gpu alone, which the experiment's
# trainer.accelerator: cpu overrode; preflight now refuses that), 13 jobs at a thread each, DIDER's epochs about 3.8
# minutes. Whether jobs side by side share the chip well is open: time one job alone first. Run from the repository
# root with hydra-core, omegaconf and antlr4 as wheels in .whl/ (carry=[".whl"]). JOBS lists NAME:OVERRIDES entries (commas
# in OVERRIDES stand for spaces); DEADLINE_S stops unfinished jobs so that what ran comes back.
# Writes under $OUT: progress.log and one <group>.tgz per group of jobs (NAME less its _sN), the run folders without
# their epoch checkpoints and figures, last.ckpt without its optimiser state.
# A dry run on a CPU: DRY=1 bash docs/journal/gpu/protocol.sh (two jobs, a few batches, trainer on the CPU).
source docs/journal/gpu/setup.sh
DEADLINE_S=${DEADLINE_S:-540}
RUNS=${RUNS:-/tmp/runs}; mkdir -p "$RUNS"
if [ -n "${DRY:-}" ]; then
  device="trainer.accelerator=cpu cuda_graph=true trainer.max_epochs=1 trainer.limit_train_batches=3 \
    trainer.limit_val_batches=1 data.num_train=64 data.num_test=32"
  JOBS=${JOBS:-"dnri_s1:model=dnri,seed=1 cand_s1:model=dider,seed=1,model/net/objective=dider_indifference"}
else
  # trainer.accelerator too: the experiment pins it to the CPU after the trainer group
  device="trainer=gpu trainer.accelerator=gpu trainer.precision=32-true"
  nvidia-smi -L; python3 -c "import torch, lightning; print(torch.__version__, lightning.__version__)"
fi
first=${JOBS%% *}; first=${first#*:}
# shellcheck disable=SC2086
python3 -m dider.run experiment=synth_protocol ${first//,/ } $device --cfg job | grep -E "^  accelerator: " \
  | tee "$OUT/progress.log"
pids=()
for job in $JOBS; do
  name=${job%%:*}; overrides=${job#*:}; overrides=${overrides//,/ }
  # shellcheck disable=SC2086  # the overrides are words
  DIDER_CACHE=/tmp/cache_$name nohup python3 -m dider.run -m experiment=synth_protocol $overrides logger=csv \
    threads=1 $device "hydra.sweep.dir=$RUNS/$name" > "$RUNS/$name.log" 2>&1 &
  pids+=($!)
done
echo "${#pids[@]} jobs started at $(( $(date +%s) - start )) s" | tee -a "$OUT/progress.log"
while :; do
  sleep 20; now=$(( $(date +%s) - start )); alive=0
  for p in "${pids[@]}"; do kill -0 "$p" 2>/dev/null && alive=$((alive + 1)); done
  { echo "-- $now s, $alive running"; for job in $JOBS; do n=${job%%:*}
      echo "$n: $(grep -E 'epoch [0-9]+/' "$RUNS/$n.log" | tail -1 | sed 's/.*- epoch/epoch/' | cut -c1-150)"; done
  } >> "$OUT/progress.log"
  [ "$alive" = 0 ] && break
  if [ "$now" -ge "$DEADLINE_S" ]; then echo "deadline: stopping $alive jobs" >> "$OUT/progress.log"
    for p in "${pids[@]}"; do kill "$p" 2>/dev/null; done; sleep 5; break; fi
done
tail -n 40 "$OUT/progress.log"
for job in $JOBS; do n=${job%%:*}; grep -E "Error|Traceback" "$RUNS/$n.log" | tail -2 | sed "s/^/$n: /"; done
python3 - "$RUNS" <<'PY'
import sys, pathlib, torch
for ckpt in pathlib.Path(sys.argv[1]).glob("*/*/checkpoints/last.ckpt"):
    blob = torch.load(ckpt, map_location="cpu", weights_only=False)
    blob.pop("optimizer_states", None)
    torch.save(blob, ckpt)
PY
cd "$RUNS" || exit 1
for group in $(for job in $JOBS; do n=${job%%:*}; echo "${n%_s*}"; done | sort -u); do
  tar czf "$OUT/$group.tgz" --exclude='epoch_*.ckpt' --exclude=figures "$group"_s* "$group"_s*.log
done
ls -la "$OUT"

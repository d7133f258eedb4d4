# Sourced by the GPU scripts here, from the repository root on a lent GPU machine: hydra-core, omegaconf and antlr4
# from the wheels in .whl/ (the image lacks them), conf/ as dider.conf, and the paths.
set -u
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
[ -e src/dider/conf ] || ln -s ../../conf src/dider/conf
export PYTHONPATH=/tmp/site:$PWD/src:$PWD/docs/journal/gpu:$PWD/tests PYTHONUNBUFFERED=1 HYDRA_FULL_ERROR=1
start=$(date +%s)

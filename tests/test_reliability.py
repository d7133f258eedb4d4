"""Reliability: atomic checkpoints, kill + resume, determinism, non-finite guards, config validation, eval."""

import json
import math
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

import dider
import dider.models.likelihood as likelihood_mod
from dider.models.checkpoint_format import FORMAT
from dider.models.plugins import Progress
from dider.models.vae import RelationalVAE
from dider.run import ConfigError, predict, train, trainer_plugins, validate_config
from dider.training.callbacks import NonFiniteError
from dider.training.checkpoint import AtomicCheckpointIO
from helpers import NO_SPARSITY
from helpers.fixtures import write_trajectories

pytestmark = pytest.mark.usefixtures("one_thread")


def identical(a: dict, b: dict) -> bool:
    """Metrics equal bit for bit, NaN (an empty metric, e.g. no interaction run) equal to NaN."""
    return a.keys() == b.keys() and all(
        a[k] == b[k] or (isinstance(a[k], float) and isinstance(b[k], float) and math.isnan(a[k]) and math.isnan(b[k]))
        for k in a)


def epoch_means(run: Path) -> dict[tuple[str, str], str]:
    """(epoch, metric) -> value of every epoch mean (train/*_epoch, val/*) the run's CSV log holds (logger=csv; a
    resumed run's log holds the epochs it ran)."""
    import csv

    with (run / "csv" / "metrics.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    return {(r["epoch"], k): v for r in rows for k, v in r.items()
            if v not in (None, "") and (k.endswith("_epoch") or k.startswith("val/"))}


def metrics_of(folder: Path) -> dict[str, float]:
    return json.loads((folder / "metrics.json").read_text())["metrics"]


# ------------------------------------------------------------------------------------------ checkpoints


def test_checkpoint_writes_are_atomic(tmp_path, monkeypatch):
    io = AtomicCheckpointIO()
    path = tmp_path / "checkpoints" / "last.ckpt"
    io.save_checkpoint({"epoch": 1, "w": torch.ones(3)}, path)
    before = path.read_bytes()
    assert torch.load(path, weights_only=True)["epoch"] == 1
    assert oct(path.stat().st_mode & 0o777) == oct(0o666 & ~_umask())  # like an ordinary open()

    real_save = torch.save

    def dies_halfway(obj, f, *a, **k):
        f.write(b"PK\x03\x04 half a checkpoint")
        raise KeyboardInterrupt  # what a kill between two writes looks like from the writer's side

    monkeypatch.setattr(torch, "save", dies_halfway)
    with pytest.raises(KeyboardInterrupt):
        io.save_checkpoint({"epoch": 2, "w": torch.zeros(3)}, path)
    monkeypatch.setattr(torch, "save", real_save)
    assert path.read_bytes() == before  # the old checkpoint is intact...
    assert [p.name for p in path.parent.iterdir()] == ["last.ckpt"]  # ...and no temporary file is left
    io.save_checkpoint({"epoch": 3, "w": torch.zeros(3)}, path)
    assert torch.load(path, weights_only=True)["epoch"] == 3


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_trainer_gets_the_atomic_checkpoint_io(make_cfg):
    plugins = trainer_plugins(make_cfg([]))
    assert any(isinstance(p, AtomicCheckpointIO) for p in plugins)


def _run_args(out: Path, cache: Path, *extra: str) -> list[str]:
    # 10 training batches per epoch so that an epoch takes long enough to be interrupted in.
    return [sys.executable, "-m", "dider.run", "experiment=smoke", "logger=none", "threads=1", "seed=3",
            "data.num_train=160", "trainer.max_epochs=4", "trainer.enable_progress_bar=false",
            f"data.cache_dir={cache}", f"hydra.run.dir={out}", *extra]


@pytest.mark.slow  # two real processes, about 25 s: make test-all (the SIGTERM resume below runs by default)
def test_killed_run_resumes_to_the_same_metrics(tmp_path, cache_dir):
    """SIGKILL a real training process during its third epoch (after epoch 1's last.ckpt), resume it with
    ckpt_path=last in the same folder: metrics.json equals the uninterrupted run's with the same seed."""
    env = dict(os.environ, HYDRA_FULL_ERROR="1")
    killed, whole = tmp_path / "killed", tmp_path / "whole"
    logs = {name: (tmp_path / f"{name}.log").open("w") for name in ("killed", "whole")}
    run = subprocess.Popen(_run_args(killed, cache_dir), cwd=tmp_path, env=env, stdout=logs["killed"],
                           stderr=subprocess.STDOUT)
    # the uninterrupted reference runs alongside (one thread each)
    ref = subprocess.Popen(_run_args(whole, cache_dir), cwd=tmp_path, env=env, stdout=logs["whole"],
                           stderr=subprocess.STDOUT)
    try:
        last = killed / "checkpoints" / "last.ckpt"
        deadline = time.monotonic() + 300
        while True:
            if run.poll() is not None:
                pytest.fail(f"the run ended (rc {run.returncode}) before it could be killed:\n"
                            f"{(tmp_path / 'killed.log').read_text()[-3000:]}")
            # writes are atomic, so whatever last.ckpt holds is a whole checkpoint
            if last.exists() and torch.load(last, map_location="cpu", weights_only=True)["epoch"] >= 1:
                run.send_signal(signal.SIGKILL)
                break
            assert time.monotonic() < deadline, "no epoch-1 checkpoint within 5 minutes"
            time.sleep(0.02)
        run.wait()
        assert run.returncode == -signal.SIGKILL
        assert not (killed / "metrics.json").exists()  # it really died mid-run
        assert torch.load(last, map_location="cpu", weights_only=True)["epoch"] < 3
        for ckpt in (killed / "checkpoints").iterdir():  # nothing half-written
            assert ckpt.suffix == ".ckpt", ckpt.name
            torch.load(ckpt, map_location="cpu", weights_only=True)

        resumed = subprocess.run(_run_args(killed, cache_dir, "ckpt_path=last"), cwd=tmp_path, env=env,
                                 capture_output=True, text=True, timeout=600)
        assert resumed.returncode == 0, resumed.stderr[-3000:]
        assert ref.wait(timeout=600) == 0, (tmp_path / "whole.log").read_text()[-3000:]
    finally:
        for p in (run, ref):
            if p.poll() is None:
                p.kill()
                p.wait()
        for f in logs.values():
            f.close()
    assert torch.load(last, map_location="cpu", weights_only=True)["epoch"] == 3
    resumed_metrics, reference = metrics_of(killed), metrics_of(whole)
    assert resumed_metrics.keys() == reference.keys() and "test/mse/h01" in reference
    assert identical(resumed_metrics, reference)


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT"])
def test_terminated_mid_epoch_exits_143_and_resumes_to_the_uninterrupted_numbers(make_cfg, tmp_path, capsys, sig):
    """A real SIGTERM (a scheduler's time limit) or Ctrl-C after batch 3 of epoch 2: exit status 143, last.ckpt saved
    with the epoch's position, the resume command printed; ckpt_path=last then trains on exactly the batches the
    uninterrupted run trained on (the rest of the interrupted epoch in its order, the same random stream), and every
    test metric equals the uninterrupted run's."""
    base = ["seed=3", "logger=csv", "trainer.max_epochs=2", "data.num_train=96"]  # 6 batches an epoch
    whole = train(make_cfg(base, out=tmp_path / "whole"))
    stop = ["+callbacks.stop._target_=helpers.signals.TerminateAt", "+callbacks.stop.epoch=1",
            "+callbacks.stop.batch=2", f"+callbacks.stop.signal={sig}"]
    with pytest.raises(SystemExit) as stopped:
        train(make_cfg(base + stop, out=tmp_path / "run"))
    assert stopped.value.code == 143
    assert "terminated (SIGTERM or Ctrl-C); resume with: python -m dider.run mode=train" in capsys.readouterr().err
    assert "terminated (SIGTERM or Ctrl-C) at epoch 1, step 9: saved" in (tmp_path / "run" / "run.log").read_text()
    last = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert last["global_step"] == 9 and last["dider_epoch_position"]["done"] == 3
    assert not (tmp_path / "run" / "metrics.json").exists()
    resumed = train(make_cfg(base + ["ckpt_path=last"], out=tmp_path / "run"))
    assert "test/mse/h01" in whole and identical(resumed, whole)
    # the interrupted epoch's logged means cover its batches before the stop too
    logged = epoch_means(tmp_path / "run")
    assert ("1", "train/loss_epoch") in logged and logged.items() <= epoch_means(tmp_path / "whole").items()


def test_an_interrupted_evaluation_prints_the_command_that_repeats_it(make_cfg, tmp_path, capsys):
    """SIGTERM in an evaluation's test pass: the printed command is an evaluation (mode=eval, its checkpoint), and
    followed it writes the evaluation's metrics, equal to an uninterrupted evaluation's."""
    base = ["seed=3", "logger=none", "data.num_test=48", "data.loader.eval_batch_size=16"]
    train(make_cfg(base, out=tmp_path / "train"))
    ckpt = tmp_path / "train" / "checkpoints" / "last.ckpt"
    whole = train(make_cfg([*base, "mode=eval", f"ckpt_path={ckpt}"], out=tmp_path / "whole"))
    stop = ["+callbacks.stop._target_=helpers.signals.TerminateAt", "+callbacks.stop.epoch=0",
            "+callbacks.stop.batch=0", "+callbacks.stop.loop=test"]
    with pytest.raises(SystemExit):
        train(make_cfg([*base, "mode=eval", f"ckpt_path={ckpt}", *stop], out=tmp_path / "eval"))
    command = capsys.readouterr().err.split("resume with: ", 1)[1].split()
    assert command[:4] == ["python", "-m", "dider.run", "mode=eval"] and f"ckpt_path={ckpt}" in command
    assert set(base) < set(command)  # the job's own overrides
    again = [o for o in command[3:] if not o.startswith(("hydra.run.dir=", "+callbacks.stop"))]  # the probe off
    assert identical(train(make_cfg(again, out=tmp_path / "eval")), whole)


def test_terminated_during_validation_resumes_to_the_uninterrupted_numbers(make_cfg, tmp_path):
    """SIGTERM at validation batch 1 of epoch 1 of 3: the validation finishes before the save (epoch 1 is a
    best-checkpoint candidate as in the uninterrupted run), the resumed run trains epoch 2 in the uninterrupted order,
    and every test metric and every logged epoch mean equals the uninterrupted run's."""
    base = ["seed=3", "logger=csv", "trainer.max_epochs=3", "data.num_train=64", "data.num_val=48",
            "data.loader.eval_batch_size=16"]  # 3 validation batches an epoch
    whole = train(make_cfg(base, out=tmp_path / "whole"))
    stop = ["+callbacks.stop._target_=helpers.signals.TerminateAt", "+callbacks.stop.epoch=1",
            "+callbacks.stop.batch=1", "+callbacks.stop.loop=val"]
    with pytest.raises(SystemExit) as stopped:
        train(make_cfg(base + stop, out=tmp_path / "run"))
    assert stopped.value.code == 143
    resumed = train(make_cfg(base + ["ckpt_path=last"], out=tmp_path / "run"))
    assert "test/mse/h01" in whole and identical(resumed, whole)
    logged = epoch_means(tmp_path / "run")  # the resumed run's: epoch 2 (epoch 1 validated before the save)
    assert ("2", "val/select") in logged and ("2", "train/loss_epoch") in logged
    assert logged.items() <= epoch_means(tmp_path / "whole").items()
    assert sorted(p.name for p in (tmp_path / "run" / "checkpoints").iterdir()) == sorted(
        p.name for p in (tmp_path / "whole" / "checkpoints").iterdir())


# ------------------------------------------------------------------------------------------ determinism


@pytest.mark.slow  # three runs, about 15 s: make test-all (same bits twice: tests/test_reproducibility.py)
def test_same_seed_same_metrics_other_seed_differs(make_cfg, tmp_path):
    runs = {}
    for name, seed in (("a", 4), ("b", 4), ("c", 5)):
        cfg = make_cfg([f"seed={seed}", "logger=none", "trainer.max_epochs=2"], out=tmp_path / name)
        train(cfg)
        runs[name] = metrics_of(tmp_path / name)
    assert runs["a"] == runs["b"]
    assert runs["a"]["test/mse/h01"] != runs["c"]["test/mse/h01"]
    assert runs["a"]["test/nll"] != runs["c"]["test/nll"]


def test_eval_mode_recomputes_the_test_metrics(make_cfg, tmp_path):
    """mode=eval ckpt_path=PATH reproduces the metrics written at the end of training and writes its own."""
    cfg = make_cfg(["seed=6", "logger=none", "trainer.max_epochs=2"], out=tmp_path / "train")
    trained = train(cfg)
    record = json.loads((tmp_path / "train" / "metrics.json").read_text())
    ckpt = str(tmp_path / "train" / record["checkpoint"])  # relative to the run folder
    assert record["checkpoint"].startswith("checkpoints/") and Path(ckpt).is_file()
    assert identical(record["metrics"], trained)
    torch.manual_seed(123)  # a different random state going in: evaluation must not depend on it
    cfg = make_cfg(["seed=6", "logger=none", "mode=eval", f"ckpt_path={ckpt}"], out=tmp_path / "eval")
    evaluated = train(cfg)
    own = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert own["checkpoint"] == ckpt and "mode=eval" in own["overrides"]
    assert identical(own["metrics"], evaluated) and identical(evaluated, record["metrics"])


# ------------------------------------------------------------------------------------------ guards


def test_non_finite_loss_stops_naming_step_batch_and_term(make_cfg, tmp_path, monkeypatch):
    calls = []
    real = likelihood_mod.gaussian_nll

    def nan_on_third_call(*args, **kwargs):
        calls.append(1)
        out = real(*args, **kwargs)
        return out * float("nan") if len(calls) == 3 else out

    monkeypatch.setattr(likelihood_mod, "gaussian_nll", nan_on_third_call)
    cfg = make_cfg(["logger=none", "model=dnri"], out=tmp_path / "run")  # 4 batches per epoch
    with pytest.raises(NonFiniteError, match=r"non-finite loss at step 2, batch 2 of epoch 0: term nll \(nll=nan"):
        train(cfg)
    assert not (tmp_path / "run" / "metrics.json").exists()


def test_the_gpus_deferred_check_names_the_first_bad_step(make_cfg, tmp_path, monkeypatch):
    """On a GPU the guard accumulates its checks on the device and reads them every n steps (no per-step read-back);
    forced here with n = 3: a NaN at step 1 stops the run at step 3, naming step 1."""
    from dider.training import callbacks

    calls, real = [], likelihood_mod.gaussian_nll

    def nan_on_second_call(*args, **kwargs):
        calls.append(1)
        out = real(*args, **kwargs)
        return out * float("nan") if len(calls) == 2 else out

    monkeypatch.setattr(likelihood_mod, "gaussian_nll", nan_on_second_call)
    init = callbacks.FiniteGuard.__init__
    monkeypatch.setattr(callbacks.FiniteGuard, "__init__", lambda self, every=None: init(self, every=3))
    cfg = make_cfg(["logger=none", "model=dnri"], out=tmp_path / "run")
    with pytest.raises(NonFiniteError, match=r"non-finite loss at step 1 \(found at step 3: the checks are read "
                                             r"every 3 steps"):
        train(cfg)


def test_non_finite_gradient_stops_naming_the_term(make_cfg, tmp_path, monkeypatch):
    real = RelationalVAE.infer

    def infer(self, batch, hard, progress=Progress()):
        out = real(self, batch, hard, progress)
        if self.training and progress.step >= 1:
            # finite value (0), NaN gradient (d sqrt(u)/du at 0 is inf, times du/dw = 0)
            w = next(self.decoder.parameters())
            out.terms["kl_duration"] = out.terms["kl_duration"] + (w.sum() * 0).sqrt()
        return out

    monkeypatch.setattr(RelationalVAE, "infer", infer)
    cfg = make_cfg(["logger=none", "model=dider"], out=tmp_path / "run")
    with pytest.raises(NonFiniteError, match=r"non-finite gradient at step 1, batch 1 of epoch 0: from loss term "
                                             r"kl_duration;"):
        train(cfg)


def test_a_diverging_dider_stops_with_the_non_finite_error(make_cfg, tmp_path):
    """lr=1e20: the first step makes every weight NaN, and DIDER's segment loop must still end so that the guard
    stops the run at step 1 (it used to spin forever on NaN hazards)."""
    cfg = make_cfg(["logger=none", "model=dider", "model.optimizer.lr=1e20"], out=tmp_path / "run")
    with pytest.raises(NonFiniteError, match=r"non-finite (loss|gradient) at step 1, "):
        train(cfg)


def test_a_checkpoint_with_nan_weights_is_named_in_eval_predict_and_load(make_cfg, tmp_path):
    train(make_cfg(["logger=none", "model=dider"], out=tmp_path / "run"))
    ckpt = tmp_path / "run" / "checkpoints" / "last.ckpt"
    state = torch.load(ckpt, weights_only=True)
    key = next(k for k in state["state_dict"] if k.endswith("weight"))
    state["state_dict"][key] = state["state_dict"][key] * float("nan")
    torch.save(state, ckpt)
    named = rf"{re.escape(str(ckpt))}: 1 weight tensor\(s\) hold NaN or inf \(e.g. {re.escape(key)}\)"
    with pytest.raises(ValueError, match=named):
        dider.load(ckpt)
    with pytest.raises(ValueError, match=named):
        train(make_cfg(["logger=none", "model=dider", "mode=eval", f"ckpt_path={ckpt}"], out=tmp_path / "eval"))
    with pytest.raises(ValueError, match=named):
        predict(make_cfg(["mode=predict", f"ckpt_path={ckpt}", "data=trajectories",
                          f"data.source.path={_npz(tmp_path)}"], out=tmp_path / "predict"))


def _npz(tmp_path: Path) -> Path:
    return write_trajectories(tmp_path / "new.npz", num=4, steps=12) and tmp_path / "new.npz"


# ------------------------------------------------------------------------------------------ config checks

BAD_CONFIGS = [
    (["model.num_edges=1"], r"model.num_edges=1: must be >= 2"),
    (["protocol.burn_in=50"], r"protocol.burn_in=50: must be shorter than the clips \(data.source.num_steps=50\)"),
    (["data.source.num_steps=20",
     "protocol.horizons=[1,5,16]"], r"protocol.horizons=\[1, 5, 16\]: each must lie in 1..15"),
    (["protocol.horizons=[0,5]"], r"protocol.horizons=\[0, 5\]"),
    (["model=dider", "model.net.duration.rate=1.5"], r"model.net.duration.rate=1.5: must lie in \(0.0, 1.0\)"),
    (["model.net.objective.kl_edge.capacity=-0.5"], r"model.net.objective.kl_edge.capacity=-0.5: must be >= 0"),
    (["model.net.objective.kl_duration.weight=-1"], r"model.net.objective.kl_duration.weight=-1: must be >= 0"),
    (["data=ind", "data.source.root=/no/such/inD"], r"data.source.root=/no/such/inD: no such folder"),
    (["data=trajectories", "data.source.path=/no/such/file.npz"], r"data.source.path=/no/such/file.npz: no such file"),
    (["data=ind", "data.windows.seq_len=20", "protocol.burn_in=20"],
     r"protocol.burn_in=20: must be shorter .*data.windows.seq_len=20"),
    (["data=springs", "data.source.num_frames=20", "protocol.burn_in=20"],
     r"protocol.burn_in=20: must be shorter .*data.source.num_frames=20"),
    (["mode=eval"], r"ckpt_path: mode=eval needs ckpt_path"),
    (["ckpt_path=/no/such.ckpt"], r"ckpt_path=/no/such.ckpt: no such checkpoint file"),
    (["protocol.burn_in=0", "model=dider"], r"configuration:\n  - protocol.burn_in=0: must be >= 1$"),  # not again
    (["+model.gumbel_tau=0.3"], r"model.gumbel_tau: not a setting of .* \(model.net.gumbel_tau\)"),
    (["protocol.burn_in_mode=sideways"], r"configuration:\n  - protocol.burn_in_mode='sideways': expected one of "
                                         r"\['global', 'per_agent'\]$"),  # once, not again as data.* and model.*
    (["data.num_train=0"], r"data.num_train=0: must be >= 1"),
    (["data.loader.batch_size=0"], r"data.loader.batch_size=0: must be >= 1"),
    (["data.loader.num_workers=1.5"], r"data.loader.num_workers=1.5: must be an integer"),
    (["+data.loader.batchsize=8"], r"data.loader.batchsize: no such setting \(expected one of \['batch_size'"),
    (["compile=maybe"], r"compile='maybe': expected true or false"),
    (["trainer.max_epochs=abc"], r"trainer.max_epochs='abc': must be an integer"),
    (["model.optimizer.lr=abc"], r"model.optimizer.lr='abc': must be a number"),
    (["model.optimizer.lr=-1"], r"model.optimizer.lr=-1: must be > 0"),
    (["model.optimizer.lr=0"], r"model.optimizer.lr=0: must be > 0"),
    (["model.num_edges=2.5"], r"model.num_edges=2.5: must be an integer"),
    (["model.net.encoder.hidden=abc"], r"model.net.encoder.hidden='abc': must be an integer"),
    (["seed=abc"], r"seed='abc': must be an integer"),
    (["threads=-1"], r"threads=-1: must be >= 1"),
    (["deterministic=maybe"], r"deterministic='maybe': expected one of \[True, False, 'warn'\]"),
    (["data=table", "data.source.path=/no/t.csv", "data.seed=abc"], r"data.seed='abc': must be an integer"),
    (["data=table", "data.source.path=/no/t.csv", "data.source.columns=abc"],
     r"data.source.columns='abc': expected a mapping of key -> column name"),
]


@pytest.mark.parametrize("overrides, match", BAD_CONFIGS, ids=[b[1][:30] for b in BAD_CONFIGS])
def test_config_errors_name_the_key(make_cfg, overrides, match):
    with pytest.raises(ConfigError, match=match):
        validate_config(make_cfg(overrides))


def test_an_optimized_metric_the_model_never_logs_is_refused_before_training(make_cfg, tmp_path):
    with pytest.raises(ConfigError, match=r"optimized_metric=val/nope: the model logs no such metric; e.g. val/"):
        train(make_cfg(["optimized_metric=val/nope", "logger=none"], out=tmp_path / "run"))
    assert not list((tmp_path / "run").glob("checkpoints/*.ckpt"))


def test_config_checks_run_before_any_work(make_cfg, tmp_path, monkeypatch):
    def boom(*a, **k):
        raise AssertionError("work started")

    monkeypatch.setattr("dider.run.instantiate", boom)
    cfg = make_cfg(["model.num_edges=1", "model.net.objective.kl_edge.capacity=-1", "protocol.burn_in=60"],
                   out=tmp_path / "run")
    with pytest.raises(ConfigError) as info:
        train(cfg)
    message = str(info.value)  # every problem at once
    for key in ("model.num_edges=1", "model.net.objective.kl_edge.capacity=-1", "protocol.burn_in=60"):
        assert key in message
    assert not (tmp_path / "run").exists()


def test_valid_configs_pass(make_cfg, tmp_path):
    for overrides in ([], ["model=dnri"], ["model=nri"], ["data=ind"], ["data=basketball"], ["data=trajectories"],
                      ["data=ind", f"data.source.root={tmp_path}"], ["model.net.duration.rate=0.1"]):
        validate_config(make_cfg(overrides))
    npz = tmp_path / "t.npz"
    npz.write_bytes(b"")
    validate_config(make_cfg(["data=trajectories", f"data.source.path={npz}"]))


# ------------------------------------------------------------------------------------------ run folders


def test_horizons_of_one_run_to_the_end(make_cfg, tmp_path):
    metrics = train(make_cfg(["protocol.horizons=[1]", "model=dnri", "logger=none", "trainer.max_epochs=2"],
                             out=tmp_path / "run"))
    assert "test/mse/h01" in metrics and not any(k.startswith("test/mse/h15") for k in metrics)


def test_a_fresh_run_does_not_overwrite_a_run(make_cfg, tmp_path):
    out = tmp_path / "run"
    train(make_cfg(["logger=none", "model=dnri"], out=out))
    with pytest.raises(ConfigError, match=r"already holds a run \(metrics.json, checkpoints/.*ckpt_path=last"):
        train(make_cfg(["logger=none", "model=dnri"], out=out))


def test_a_live_run_locks_its_folder(make_cfg, tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (out / ".dider.lock").write_text(json.dumps({"pid": other.pid, "host": socket.gethostname()}))
        with pytest.raises(ConfigError, match=rf"being written by another run \(pid {other.pid}"):
            train(make_cfg(["logger=none", "model=dnri"], out=out))
    finally:
        other.kill()
        other.wait()
    train(make_cfg(["logger=none", "model=dnri"], out=out))  # its writer is gone: the stale lock is taken over
    assert (out / "metrics.json").exists() and not (out / ".dider.lock").exists()


def test_terminated_while_drawing_the_figures_says_so_and_leaves_no_partial_file(make_cfg, tmp_path, monkeypatch,
                                                                                  capsys):
    """SIGTERM half-way through a figure's PNG (after metrics.json): exit 143 with a word (console and run.log), no
    temporary file; the printed command draws them, the metrics unchanged."""
    import matplotlib.figure

    out = tmp_path / "run"
    base = ["seed=3", "logger=none", "callbacks.timelines.num_clips=2"]
    savefig, calls = matplotlib.figure.Figure.savefig, []

    def interrupted(self, f, *args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            f.write(b"\x89PNG half")
            os.kill(os.getpid(), signal.SIGTERM)
        return savefig(self, f, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", interrupted)
    with pytest.raises(SystemExit) as stopped:
        train(make_cfg(base, out=out))
    assert stopped.value.code == 143
    assert "while drawing the figures (the results are written); draw them with:" in capsys.readouterr().err
    assert "while drawing the figures" in (out / "run.log").read_text()
    assert not list(out.rglob("*.tmp")) and (out / "metrics.json").is_file()
    first = metrics_of(out)
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", savefig)
    train(make_cfg([*base, "ckpt_path=last"], out=out))
    assert identical(metrics_of(out), first) and len(list((out / "figures").glob("*.png"))) >= 4


def test_a_run_resumed_from_a_best_checkpoint_keeps_no_stray(make_cfg, tmp_path, caplog):
    """last.ckpt lost (a kill during its write): ckpt_path=last resumes from the best epoch's file; once a better
    epoch replaces it, that file goes too (Lightning keeps the file a run resumed from), leaving save_top_k + last."""
    out = tmp_path / "run"
    base = ["seed=2", "logger=none", "callbacks.timelines.num_clips=0", "model=dnri"]
    train(make_cfg([*base, "trainer.max_epochs=1"], out=out))
    (out / "checkpoints" / "last.ckpt").unlink()
    (resumed,) = (out / "checkpoints").glob("epoch_*.ckpt")
    with caplog.at_level("INFO", logger="dider.training.interrupt"):
        train(make_cfg([*base, "trainer.max_epochs=4", "ckpt_path=last"], out=out))
    files = sorted(p.name for p in (out / "checkpoints").iterdir())
    assert len(files) == 2 and "last.ckpt" in files, files
    if resumed.name not in files:  # displaced by a better epoch (this seed: yes)
        assert f"removing {resumed}" in caplog.text


def test_a_lock_that_cannot_be_taken_over_says_which_file_and_how_to_proceed(tmp_path, monkeypatch):
    from dider.training.run_lock import LOCK, RunLock, _started

    lock = tmp_path / LOCK
    lock.write_text(json.dumps({"pid": 1, "host": "another-machine"}))
    with pytest.raises(ConfigError, match=rf"pid 1 on another-machine, its lock {lock}\); wait for it, or use another "
                                          rf"hydra.run.dir. If that run is gone .*remove {lock} and run again"):
        RunLock(tmp_path).__enter__()
    # our own pid, a lock we do not hold (a container restarted as the same pid): stale
    lock.write_text(json.dumps({"pid": os.getpid(), "host": socket.gethostname()}))
    with RunLock(tmp_path) as held:
        assert held.held and json.loads(lock.read_text())["started"] == _started(os.getpid())
        with pytest.raises(ConfigError, match="being written by another run"):  # held by us: live
            RunLock(tmp_path).__enter__()
    # a live pid that another process has since been given (its start time differs): stale
    lock.write_text(json.dumps({"pid": os.getppid(), "host": socket.gethostname(), "started": -1}))
    with RunLock(tmp_path) as held:
        assert held.held
    assert not lock.exists()


def test_a_full_disk_at_the_start_names_the_lock_and_leaves_none(tmp_path, monkeypatch):
    from dider.training.run_lock import LOCK, RunLock

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(json, "dump", full)
    with pytest.raises(OSError, match=rf"{tmp_path / LOCK}: could not write the run folder's lock \(No space left"):
        RunLock(tmp_path).__enter__()
    assert not (tmp_path / LOCK).exists()


def test_a_checkpoint_of_another_model_is_named(make_cfg, tmp_path):
    train(make_cfg(["logger=none", "model=dider"], out=tmp_path / "run"))
    ckpt = tmp_path / "run" / "checkpoints" / "last.ckpt"
    for overrides, expected in ((["model=dider_skid"], r"model.name: checkpoint 'dider', config 'dider_skid'"),
                                (["model=dider", "model.num_edges=4"], r"model.num_edges: checkpoint 2, config 4"),
                                (["model=dnri"], r"model.net.duration._target_: checkpoint")):
        with pytest.raises(ConfigError, match=expected):
            train(make_cfg([*overrides, "logger=none", "mode=eval", f"ckpt_path={ckpt}"], out=tmp_path / "eval"))
    notes = tmp_path / "notes.txt"
    notes.write_text("hello")
    with pytest.raises(ConfigError, match=r"notes.txt: not a readable dider checkpoint"):
        train(make_cfg(["logger=none", "mode=eval", f"ckpt_path={notes}"], out=tmp_path / "eval"))


def test_resume_last_in_a_new_folder_is_an_error(make_cfg, tmp_path):
    with pytest.raises(FileNotFoundError, match=r"ckpt_path=last: no checkpoint in .*a new run folder"):
        train(make_cfg(["ckpt_path=last"], out=tmp_path / "new"))
    cfg = make_cfg(["ckpt_path=last", "logger=none", "model=dnri", f"hydra.run.dir={tmp_path / 'job'}"],
                   out=tmp_path / "job")
    assert "test/mse/h01" in train(cfg)  # a named folder with no run yet: a restartable job's first start


def test_warnings_name_suspicious_settings(make_cfg, caplog):
    with caplog.at_level("WARNING"):
        validate_config(make_cfg(["trainer.max_epochs=0", "+foo=1"]))
    assert "trainer.max_epochs=0: nothing is trained" in caplog.text
    assert "foo: top-level key(s) that nothing reads" in caplog.text


@pytest.mark.parametrize("native", [True, False])
def test_bf16_on_a_cpu_that_emulates_it_is_named(make_cfg, caplog, monkeypatch, native):
    import dider.training.preflight

    monkeypatch.setattr(dider.training.preflight, "native_bf16", lambda device: native)
    with caplog.at_level("WARNING"):
        validate_config(make_cfg(["trainer.precision=bf16-mixed", "trainer.accelerator=cpu"]))
    assert ("trainer.precision=bf16-mixed: this CPU has no native bf16" in caplog.text) is not native


def test_a_gpu_trainer_that_an_experiment_puts_back_on_the_cpu_is_refused(make_cfg):
    # The CPU-sized experiments pin trainer.accelerator: cpu after the trainer group; trainer=gpu alone would
    # train on the CPU without a word.
    with pytest.raises(ConfigError, match=r"trainer=gpu with trainer\.accelerator=cpu .*add trainer\.accelerator=gpu"):
        validate_config(make_cfg(["experiment=synth_protocol", "trainer=gpu"], tiny=False))
    cfg = make_cfg(["experiment=synth_protocol", "trainer=gpu", "trainer.accelerator=gpu"], tiny=False)
    assert cfg.trainer.accelerator == "gpu"
    validate_config(cfg)


def test_a_corrupt_cache_is_named_moved_aside_and_rebuilt(make_cfg, tmp_path, caplog):
    from dider.data.cache import load_or_build

    path = tmp_path / "cache" / "blob.pt"
    path.parent.mkdir()
    path.write_bytes(b"not a torch file")
    with caplog.at_level("WARNING"):
        assert load_or_build(path, lambda: {"x": torch.ones(2)})["x"].sum() == 2
    assert "blob.pt cannot be read" in caplog.text and (tmp_path / "cache" / "blob.pt.corrupt").exists()
    assert torch.load(path, weights_only=True)["x"].sum() == 2  # rebuilt, whole

    class Planted:  # a pickle that would run code when loaded without weights_only
        def __reduce__(self):
            return (Path.touch, (tmp_path / "pwned",))

    torch.save({"x": Planted()}, path)
    assert load_or_build(path, lambda: {"x": torch.zeros(1)})["x"].sum() == 0
    assert not (tmp_path / "pwned").exists()

    stale = path.parent / ".blob.pt.abc.tmp"
    stale.write_bytes(b"x" * 10)
    os.utime(stale, (time.time() - 7200, time.time() - 7200))
    fresh = path.parent / ".other.pt.def.tmp"
    fresh.write_bytes(b"y")
    load_or_build(path, lambda: {})
    assert not stale.exists() and fresh.exists()  # a live writer's file (young) is left alone


def test_a_corrupt_background_image_costs_no_results(make_cfg, tmp_path, caplog):
    from helpers.fixtures import write_ind_root

    root = write_ind_root(tmp_path / "inD", num_recordings=3, num_frames=600, num_tracks=5)
    (root / "02_background.png").write_bytes(b"garbage, not a PNG")
    with caplog.at_level("WARNING"):
        train(make_cfg(["data=ind", f"data.source.root={root}", "data.split=[1,1,1]", "data.num_train=8",
                        "data.num_val=4", "data.num_test=4", "logger=none", "model=dnri", *NO_SPARSITY],
                       out=tmp_path / "run"))
    assert (tmp_path / "run" / "metrics.json").exists() and (tmp_path / "run" / "segments.json").exists()
    assert "02_background.png: cannot read the background image" in caplog.text


def test_a_failed_run_says_so_in_its_folder(tmp_path):
    out, bad = tmp_path / "run", tmp_path / "bad.npz"
    bad.write_bytes(b"garbage")  # passes the config check (the file exists), fails when read
    proc = subprocess.run([sys.executable, "-m", "dider.run", "experiment=smoke", "data=trajectories",
                           f"data.source.path={bad}",
                           f"hydra.run.dir={out}"], capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, HYDRA_FULL_ERROR="1"), cwd=tmp_path)
    assert proc.returncode != 0
    failed = json.loads((out / "failed.json").read_text())
    assert failed["status"] == "failed" and "bad.npz" in failed["error"]
    assert "bad.npz" in (out / "run.log").read_text()  # the traceback reaches the run's own log


def _bad_npz(tmp: Path) -> list[str]:
    import numpy as np

    pos = np.random.default_rng(0).normal(size=(20, 12, 3, 2))
    pos[3, 4, 1, 0] = 1e300  # finite in float64, inf in float32
    np.savez(tmp / "big.npz", positions=pos)
    return ["data=trajectories", f"data.source.path={tmp / 'big.npz'}", "protocol.horizons=[1,5]"]


def _bad_csv(tmp: Path) -> list[str]:
    from helpers.fixtures import edit_csv, write_ind_root

    root = write_ind_root(tmp / "inD", num_recordings=3, num_frames=300, num_tracks=4)

    def pad(df):
        df["xCenter"] = df["xCenter"].astype(object)
        df.loc[7, "xCenter"] = " nan"
        return df

    edit_csv(root / "01_tracks.csv", pad)
    return ["data=ind", f"data.source.root={root}", "data.split=[1,1,1]"]


PROBES = [  # (what the command line gets, what the error must name)
    (lambda tmp: ["model.optimizer.lr=abc"], r"model.optimizer.lr='abc': must be a number"),
    (_bad_npz, r"big.npz: key 'positions'.*beyond float32's range"),
    (_bad_csv, r"01_tracks.csv: column 'xCenter', line 9: ' nan' is not a number"),
]


@pytest.mark.parametrize("make, named", PROBES, ids=["config", "npz-overflow", "csv-padded-nan"])
def test_bad_input_fails_named_with_nothing_left_behind(tmp_path, make, named):
    """The command line a user runs: a non-zero exit, the error naming the key or file (and cell), and no
    checkpoint or metrics in the run folder."""
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "dider.run", "experiment=smoke", "logger=none", *make(tmp_path),
                           f"hydra.run.dir={out}", f"data.cache_dir={tmp_path / 'cache'}"], capture_output=True,
                          text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode != 0
    assert re.search(named, proc.stderr), proc.stderr[-2000:]
    assert not (out / "metrics.json").exists() and not list(out.glob("checkpoints/*.ckpt"))
    assert not list((tmp_path / "cache").rglob("*.tmp"))  # no half-written cache


def test_a_refused_config_leaves_no_folder_and_a_refused_sweep_job_says_why(tmp_path):
    """The preflight refuses model.num_edges=1: a single run's new folder is gone (no 0-byte run.log either); a
    sweep's job folder keeps failed.json with the reason, which report shows instead of "missing"."""
    args = [sys.executable, "-m", "dider.run", "model.num_edges=1"]
    single = subprocess.run([*args, f"hydra.run.dir={tmp_path / 'one'}"], capture_output=True, text=True,
                            timeout=300, cwd=tmp_path)
    assert single.returncode != 0 and "model.num_edges=1: must be >= 2" in single.stderr
    assert not (tmp_path / "one").exists()
    sweep = subprocess.run([*args[:3], "-m", args[3], f"hydra.sweep.dir={tmp_path / 'sweep'}"], capture_output=True,
                           text=True, timeout=300, cwd=tmp_path)
    assert sweep.returncode != 0
    job = tmp_path / "sweep" / "model.num_edges=1"
    assert sorted(p.name for p in job.iterdir()) == ["failed.json"]
    assert "model.num_edges=1: must be >= 2" in json.loads((job / "failed.json").read_text())["error"]


def test_a_success_clears_an_earlier_failure_and_a_failed_record_never_hides_the_error(make_cfg, tmp_path,
                                                                                         monkeypatch, caplog):
    from dider.training import runfolder

    out = tmp_path / "run"
    out.mkdir()
    (out / "failed.json").write_text('{"status": "failed", "error": "an earlier attempt"}')
    train(make_cfg(["logger=none", "callbacks.timelines.num_clips=0"], out=out))
    assert (out / "metrics.json").is_file() and not (out / "failed.json").exists()

    runfolder.OPENED.add(out.resolve())

    def full(path, text):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(runfolder, "atomic_write_text", full)
    with caplog.at_level("WARNING"):
        runfolder.mark_failed(out, ValueError("the real error"))  # returns: the caller re-raises the real one
    assert "could not record the failure in" in caplog.text and "failed.json" in caplog.text


def test_a_full_disk_is_named(tmp_path, monkeypatch):
    """torch.save reports a full disk as 'inline_container.cc ... unexpected pos': the error names the file,
    the free space and whether the folder is writable, and leaves no temporary file."""
    from dider.io import atomic_torch_save

    def full(*args, **kwargs):
        raise RuntimeError("[enforce fail at inline_container.cc:626] . unexpected pos 64 vs 0")

    monkeypatch.setattr(torch, "save", full)
    with pytest.raises(OSError, match=r"last.ckpt: could not be written \(RuntimeError: .*unexpected pos.*MiB free on "
                                      r"its disk, folder writable"):
        atomic_torch_save({"x": 1}, tmp_path / "last.ckpt")
    assert list(tmp_path.iterdir()) == []


def test_resume_after_a_kill_during_the_first_last_ckpt_write(tmp_path, caplog):
    """A run killed while writing its first last.ckpt leaves the best checkpoint and a temporary file: ckpt_path=last
    removes the temporary file and resumes from the newest complete checkpoint (the most optimiser steps)."""
    from dider.training.runfolder import resolve_ckpt, sweep_partial_writes

    folder = tmp_path / "checkpoints"
    folder.mkdir()
    for name, step in (("epoch_000.ckpt", 10), ("epoch_001.ckpt", 20)):  # complete checkpoints (of today's format)
        torch.save({"global_step": step, "state_dict": {}, "hyper_parameters": {}, "dider": {"format": FORMAT}},
                   folder / name)
    (folder / "broken.ckpt").write_bytes(b"PK\x03\x04 half")
    (folder / ".last.ckpt.x1y2.tmp").write_bytes(b"PK\x03\x04 half a checkpoint")
    (tmp_path / "figures").mkdir()
    (tmp_path / "figures" / ".timeline_00.png.a1b2.tmp").write_bytes(b"\x89PNG half")  # a figure's write
    with caplog.at_level("WARNING", logger="dider.training.runfolder"):
        assert resolve_ckpt("last", tmp_path, folder_given=True) == str(folder / "epoch_001.ckpt")
        sweep_partial_writes(tmp_path)  # what the resumed run does under the folder's lock
    assert not list(tmp_path.rglob("*.tmp"))
    assert "last.ckpt is missing" in caplog.text and "removing the temporary file" in caplog.text


def test_horizons_are_whole_steps_on_every_data_set(make_cfg):
    for data in ("synth", "trajectories"):
        with pytest.raises(ConfigError, match=r"protocol.horizons=\[1, 2.5\]: each must be a whole number of steps"):
            validate_config(make_cfg([f"data={data}", "protocol.horizons=[1,2.5]"]))

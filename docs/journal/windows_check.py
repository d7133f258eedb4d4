"""What every data config and experiment feeds the model, as hashes: each split's tensors (states, mask, edges,
packing, source ids, agent ids and classes, consistency pairs) and the prediction set's, the normaliser, the step
and the source names.

The guard of a rewrite of the data layer: run it before and after on the same machine and compare the two files
(``--compare``); equal hashes are byte-identical windows, splits and normalised tensors. Real formats read small
inputs generated here (the writers below); the synthetic sets are generated at each config's sizes.

    python docs/journal/windows_check.py --out /tmp/windows_before.json
    python docs/journal/windows_check.py --out /tmp/windows_after.json --compare /tmp/windows_before.json

``windows_baseline.json`` beside it is the output of the data layer of two modules (clips, tracks; 30 cases, all
built, with the prediction sets) on an AMD EPYC CPU with AVX-512. It equals the seven-DataModule layer's output on
every tensor both have (the prediction sets and the capped levelX case were compared with that code's); the tracks
module's datasets add ``window_start``, ``window_scene`` and ``scenes`` and name levelX's ``track_id``
``agent_ids``. On another CPU take a baseline of that code first.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from hydra.utils import instantiate

from dider.bench.fake_levelx import write_levelx_recording
from dider.data.example import example_tracks
from dider.data.readers.nri_files import write_nri_split
from dider.data.simulators.particles import simulate_particles
from dider.data.simulators.push import simulate_push
from dider.graph import num_edges

# The small inputs of the real formats, written here as the baseline's were (the same writers, seeds and sizes as
# the tests' fixture writers of tests/helpers/fixtures.py, test_dnri_files.py and test_readers.py had when
# windows_baseline.json was made), so that a comparison with it reads the same files.
IND_LOCATIONS = {0: 4, 1: 4, 2: 1, 3: 1, 4: 2, 5: 3}  # mirroring inD's layout (00-06 location 4, 07-17 location 1)


def write_ind_root(root: Path, num_recordings: int, num_frames: int) -> None:
    """Fake levelX recordings 00, 01, ... of ``num_frames`` frames at 25 Hz (6 tracks, 2 parked) in ``root``."""
    for r in range(num_recordings):
        write_levelx_recording(root, r, num_frames=num_frames, num_tracks=6, num_parked=2, seed=r,
                               location_id=IND_LOCATIONS.get(r, 1))


def bball_positions(rng: np.random.Generator, num: int, steps: int, agents: int) -> np.ndarray:
    """Random walks inside the 94 x 50 ft court: [num, steps, agents, 2] float64 (feet)."""
    start = rng.uniform([0.0, 0.0], [47.0, 50.0], (num, 1, agents, 2))
    walk = np.cumsum(rng.normal(0.0, 0.8, (num, steps, agents, 2)), axis=1)
    return np.clip(start + walk, [0.0, 0.0], [94.0, 50.0])


def write_zhan(root: Path) -> None:
    """Zhan et al.'s npz files: key 'data', (S, 50, 22) = ball + 5 offence + 5 defence (x, y); 40 and 12 clips."""
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for name, num in (("train.npz", 40), ("test.npz", 12)):
        np.savez(root / name, data=bball_positions(rng, num, 50, 11).reshape(num, 50, 22))


def write_dnri_bball(root: Path) -> None:
    """DNRI's basketball npy files: {loc,vel}_{split}_bball.npy, each [S, 49, 5, 2]."""
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for split, num in {"train": 30, "valid": 8, "test": 10}.items():
        loc = bball_positions(rng, num, 50, 5)
        np.save(root / f"loc_{split}_bball.npy", loc[:, 1:])
        np.save(root / f"vel_{split}_bball.npy", np.diff(loc, axis=1))


def write_trajectories(path: Path, num: int, steps: int, agents: int) -> None:
    """A bring-your-own npz of random walks, the last agent leaving after half the clip (NaN positions and a mask),
    a random edge type per step and directed edge."""
    rng = np.random.default_rng(0)
    positions = np.cumsum(rng.normal(0, 0.1, (num, steps, agents, 2)), axis=1)
    mask = np.ones((num, steps, agents), bool)
    mask[:, steps // 2:, -1] = False
    positions[~mask] = np.nan
    edges = rng.integers(0, 3, (num, steps, num_edges(agents)))
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, positions=positions, mask=mask, edges=edges)


def write_scenes(folder: Path, scenes: int = 5, frames: int = 36, people: int = 4) -> None:
    """ETH/UCY-style files: people walking at about 1.3 m/s, a frame number every 10 (every 6 in the first file, as
    ETH's own), tab-separated, one file a scene."""
    rng = np.random.default_rng(0)
    folder.mkdir(parents=True, exist_ok=True)
    for s in range(scenes):
        step = 6 if s == 0 else 10
        start, heading = rng.uniform(-5, 5, (people, 2)), rng.uniform(0, 2 * np.pi, people)
        velocity = 1.3 * np.stack([np.cos(heading), np.sin(heading)], 1)
        lines = []
        for f in range(frames):
            for p in range(people):
                x, y = start[p] + velocity[p] * f * 0.4 + rng.normal(0, 0.02, 2)
                lines.append(f"{(f + 3) * step}\t{p + 1}\t{x:.3f}\t{y:.3f}")
        (folder / f"scene{s}.txt").write_text("\n".join(lines) + "\n")


def write_dnri(root: Path, steps: int) -> None:
    """The DNRI code's six synthetic files: float feats [S, T, 3, 4] and float 0/1 edges [S, T, 6]; 8, 3, 5 clips."""
    root.mkdir(parents=True, exist_ok=True)
    for i, (split, num) in enumerate({"train": 8, "val": 3, "test": 5}.items()):
        feats, edges = simulate_push(num, steps, push_factor=0.05, seed=10 + i)
        torch.save(feats, root / f"{split}_feats")
        torch.save(edges.float(), root / f"{split}_edges")


def inputs(root: Path) -> dict[str, str]:
    """Small inputs of every real format under ``root``: name -> path."""
    write_ind_root(root / "ind", num_recordings=5, num_frames=2200)
    write_zhan(root / "zhan")
    write_dnri_bball(root / "dnri_bball")
    write_trajectories(root / "traj.npz", num=40, steps=30, agents=3)
    example_tracks(scenes=6).to_csv(root / "table.csv", index=False)
    write_scenes(root / "eth")
    write_dnri(root / "dnri_files", steps=50)
    for i, split in enumerate(("train", "val", "test")):
        loc, vel, edges = simulate_particles("springs", 6, 49, 5, 100, 0.0, seed=i)
        write_nri_split(root / "nri", split, "_springs5", loc, vel, edges)
    return {k: str(root / k) for k in ("ind", "zhan", "dnri_bball", "traj.npz", "table.csv", "eth", "dnri_files",
                                       "nri")}


def cases(p: dict[str, str]) -> dict[str, list[str]]:
    """name -> overrides: every data config, then every experiment's data node on the same inputs."""
    small = ["data.num_train=300", "data.num_val=50", "data.num_test=100"]  # the generated sets' defaults are 40k
    levelx = [f"data.source.root={p['ind']}", "data.split=[3,1,1]"]
    out = {
        "synth": ["data=synth", *small], "synth_step": ["data=synth", "data.source.push=step", *small],
        "springs": ["data=springs", *small], "charged": ["data=charged", *small],
        "nri_files": ["data=nri_files", f"data.source.root={p['nri']}"],
        "dnri_files": ["data=dnri_files", f"data.source.root={p['dnri_files']}"],
        "basketball_zhan": ["data=basketball", f"data.source.root={p['zhan']}"],
        "basketball_dnri": ["data=basketball", f"data.source.root={p['dnri_bball']}"],
        "trajectories": ["data=trajectories", f"data.source.path={p['traj.npz']}"],
        "table": ["data=table", f"data.source.path={p['table.csv']}", "data.source.frame_rate=10",
                  "data.windows.downsample=2"],
        "eth_ucy": ["data=eth_ucy", f"data.source.path={p['eth']}"],
        "soccer": ["experiment=soccer", "hydra.mode=RUN"],
        "ind": ["data=ind", *levelx], "ind200": ["data=ind200", *levelx, "data.windows.seq_len=60",
                                              "protocol.horizons=[1,20]"],
        "round": ["data=round", *levelx], "unid": ["data=unid", *levelx],
        "ind_capped": ["data=ind", *levelx, "data.num_train=5", "data.num_val=2", "data.num_test=3"],
    }
    for exp in ("demo", "smoke", "synth_cpu_table", "synth_claims", "synth_protocol", "synth_long", "synth_table",
                "springs_nri", "springs_dynamic"):
        out[f"experiment={exp}"] = [f"experiment={exp}", "hydra.mode=RUN"]
    out["experiment=bball_table"] = ["experiment=bball_table", "hydra.mode=RUN", f"data.source.root={p['zhan']}"]
    for exp in ("ind50_table", "ind200_table", "edge_ablation"):
        out[f"experiment={exp}"] = [f"experiment={exp}", "hydra.mode=RUN", *levelx]
    return out


def digest(value: Any) -> Any:
    """A tensor or array -> 'dtype shape sha256'; containers recursively; other values as they are."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().contiguous()
        raw = value.view(torch.uint8) if value.dtype != torch.bool and value.numel() else value.to(torch.uint8)
        return f"{value.dtype} {list(value.shape)} {hashlib.sha256(raw.numpy().tobytes()).hexdigest()[:16]}"
    if isinstance(value, np.ndarray):
        return digest(torch.from_numpy(np.ascontiguousarray(value)))
    if isinstance(value, dict):
        return {str(k): digest(v) for k, v in sorted(value.items(), key=lambda kv: str(kv[0]))}
    if isinstance(value, list | tuple):
        return [digest(v) for v in value]
    return value if isinstance(value, int | float | str | bool | type(None)) else repr(value)


def fingerprint(overrides: list[str], cache: Path) -> dict[str, Any]:
    GlobalHydra.instance().clear()
    with initialize_config_module(version_base="1.3", config_module="dider.conf"):
        cfg = compose(config_name="config", overrides=[*overrides, f"data.cache_dir={cache}"])
    dm = instantiate(cfg.data, _convert_="all")
    dm.prepare_data()
    dm.setup("fit")
    out: dict[str, Any] = {"normalizer": digest(dm.state_dict()), "frame_step": dm.frame_step,
                           "dt": getattr(dm, "dt", None), "source_names": digest(dm.source_names)}
    for split, ds in sorted(dm.datasets.items()):
        out[split] = digest({k: v for k, v in vars(ds).items() if not k.startswith("_")})
    if dm.predicts:  # every clip of the input, with the trained normaliser
        again = instantiate(cfg.data, _convert_="all")
        again.use_normalizer(dm.normalizer)
        again.setup("predict")
        out["predict"] = digest({k: v for k, v in vars(again.datasets["predict"]).items() if not k.startswith("_")})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--compare", type=Path, help="an earlier output: list the cases that differ")
    parser.add_argument("--only", nargs="*", help="these cases only")
    args = parser.parse_args()
    torch.manual_seed(0)
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        todo = cases(inputs(tmp_path / "inputs"))
        result = {}
        for name, overrides in todo.items():
            if args.only and name not in args.only:
                continue
            try:
                result[name] = fingerprint(overrides, tmp_path / "cache")
            except Exception as e:  # a config that cannot be built is a result too (it must stay so)
                result[name] = {"error": f"{type(e).__name__}: {e}"[:300]}
            print(name, "error" if "error" in result[name] else "ok", flush=True)
    args.out.write_text(json.dumps(result, indent=1, sort_keys=True))
    if args.compare:
        before = json.loads(args.compare.read_text())
        names = set(result) if args.only else set(before) | set(result)  # --only: the cases it ran
        differ = [k for k in sorted(names) if before.get(k) != result.get(k)]
        print("differ:", differ or "none")


if __name__ == "__main__":
    main()

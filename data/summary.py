"""What a folder of recorded episodes holds: counts, hours, speed, commands and the steering distribution.

``summarize(folder)`` reads the small per-step arrays and then decodes every frame chunk (``check_frames``; off:
quick on big datasets, but a damaged frame then passes), because a file whose index reads fine can still hold
a chunk that does not decompress. A file that cannot be read is listed by name under ``corrupt`` (with the
reason under ``problems``), an episode whose actions are not finite or outside [-1, 1] under ``bad_labels``, and
``.partial`` leftovers of a killed writer under ``partial``; the rest of the folder is still summarized.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from towndrive.data.episodes import COMMAND_NAMES, EpisodeError, list_episodes, list_partials, read_episode

DEFAULT_DT_S = 0.05
STEER_BINS = 21


def summarize(folder: Path, progress: bool = False, check_frames: bool = True) -> dict[str, Any]:
    """Summary of every ``episode_*.h5`` in ``folder``; raises ``EpisodeError`` only if the folder does not exist.

    Keys: folder, episodes, frames, hours, drivers / towns / weathers ({name: {"episodes", "frames"}}),
    mean_speed_mps, command_share ({name: share of frames}), steer_hist ({"edges": 22 floats, "counts": 21 ints}),
    corrupt (file names that could not be read), problems ({name: why}), bad_labels (episodes with actions not
    finite or outside [-1, 1]), partial (``.partial`` leftovers, by name).
    """
    from tqdm import tqdm

    folder = Path(folder)
    paths = list_episodes(folder)
    episodes = frames = 0
    seconds = 0.0
    groups: dict[str, dict[str, Counter]] = {k: {"episodes": Counter(), "frames": Counter()}
                                             for k in ("drivers", "towns", "weathers")}
    commands: Counter = Counter()
    speed_sum = 0.0
    edges = np.linspace(-1.0, 1.0, STEER_BINS + 1)
    hist = np.zeros(STEER_BINS, np.int64)
    corrupt: list[str] = []
    problems: dict[str, str] = {}
    bad_labels: list[str] = []
    for path in tqdm(paths, desc="summary", unit="episode", disable=not progress):
        try:
            ep = read_episode(path, load_frames=False)
            if check_frames:
                check_frame_data(path, ep.steps)
        except EpisodeError as exc:
            corrupt.append(path.name)
            problems[path.name] = str(exc)
            continue
        actions = ep.actions.astype(np.float64)
        if actions.size and not (np.all(np.isfinite(actions)) and np.all(np.abs(actions) <= 1.0)):
            bad_labels.append(path.name)
        n = ep.steps
        episodes += 1
        frames += n
        dt = ep.attrs.get("dt_s", DEFAULT_DT_S)
        seconds += n * float(dt if isinstance(dt, int | float) and dt > 0 else DEFAULT_DT_S)
        for key, attr in (("drivers", "driver"), ("towns", "town_seed"), ("weathers", "weather")):
            name = str(ep.attrs.get(attr, "unknown"))
            groups[key]["episodes"][name] += 1
            groups[key]["frames"][name] += n
        if n:
            speed_sum += float(np.nansum(ep.speed.astype(np.float64)))
            values, counts = np.unique(ep.command.astype(np.int64), return_counts=True)
            for value, count in zip(values, counts, strict=True):
                commands[COMMAND_NAMES.get(int(value), str(int(value)))] += int(count)
            steer = np.clip(ep.actions[:, 0].astype(np.float64), -1.0, 1.0)
            hist += np.histogram(steer[np.isfinite(steer)], bins=edges)[0]
    return {
        "folder": str(folder),
        "episodes": episodes,
        "frames": frames,
        "hours": seconds / 3600.0,
        **{key: {name: {"episodes": g["episodes"][name], "frames": g["frames"][name]} for name in sorted(g["episodes"])}
           for key, g in groups.items()},
        "mean_speed_mps": speed_sum / frames if frames else float("nan"),
        "command_share": {name: commands[name] / frames for name in sorted(commands, key=_command_order)} if frames else {},
        "steer_hist": {"edges": [float(e) for e in edges], "counts": [int(c) for c in hist]},
        "corrupt": corrupt,
        "problems": problems,
        "bad_labels": bad_labels,
        "partial": [p.name for p in list_partials(folder)],
    }


def check_frame_data(path: Path, steps: int, block: int = 64) -> None:
    """Decode every frame of an episode (and its other image arrays), ``block`` frames at a time; a chunk that
    does not decompress, or an array shorter than the episode, raises ``EpisodeError`` naming the file and step."""
    try:
        with h5py.File(path, "r") as f:
            for name in ("frames", "depth", "segmentation", "stereo_right", "side_left", "side_right"):
                if name not in f:
                    continue
                ds = f[name]
                if len(ds) != steps:
                    raise EpisodeError(f"{path}: {name} has {len(ds)} rows for {steps} steps; re-record it.")
                for t in range(0, steps, block):
                    try:
                        ds[t:t + block]
                    except (OSError, ValueError, RuntimeError) as exc:
                        raise EpisodeError(f"{path}: {name} near step {t} cannot be decoded "
                                           f"({' '.join(str(exc).split())[:120]}); re-record or delete it.") from None
    except OSError as exc:
        raise EpisodeError(f"{path}: cannot read this episode ({exc}).") from None


def _duration(hours: float) -> str:
    return f"{hours:.2f} h" if hours >= 1 else f"{hours * 60:.1f} min"


def _command_order(name: str) -> tuple[int, str]:
    order = {v: k for k, v in COMMAND_NAMES.items()}
    return (order.get(name, len(order)), name)


def format_summary(summary: dict[str, Any]) -> str:
    """A readable plain-text report of ``summarize``'s result."""
    speed = summary["mean_speed_mps"]
    lines = [f"dataset      {summary['folder']}",
             f"episodes     {summary['episodes']}",
             f"frames       {summary['frames']}",
             f"hours        {summary['hours']:.3f} ({_duration(summary['hours'])})",
             "mean speed   " + (f"{speed:.2f} m/s ({speed * 3.6:.1f} km/h)" if np.isfinite(speed) else "-")]
    for key, title in (("drivers", "driver"), ("towns", "town_seed"), ("weathers", "weather")):
        lines += ["", f"{title:<20} {'episodes':>9} {'frames':>9}"]
        lines += [f"{name:<20} {row['episodes']:>9} {row['frames']:>9}" for name, row in summary[key].items()]
    lines += ["", f"{'command':<20} {'share':>9}"]
    lines += [f"{name:<20} {share:>8.1%}" for name, share in summary["command_share"].items()]
    lines += ["", "steering histogram (counts per bin)"]
    edges, counts = summary["steer_hist"]["edges"], summary["steer_hist"]["counts"]
    top = max(counts) if counts and max(counts) else 1
    for lo, hi, count in zip(edges[:-1], edges[1:], counts, strict=True):
        lines.append(f"  [{lo:+.2f}, {hi:+.2f})  {count:>9}  {'#' * round(40 * count / top)}")
    lines += ["", f"corrupt      {summary['corrupt'] if summary['corrupt'] else 'none'}"]
    lines += [f"  {name}: {why}" for name, why in summary.get("problems", {}).items()]
    bad = summary.get("bad_labels", [])
    lines.append(f"bad labels   {bad if bad else 'none'}" + (" (actions not finite or outside [-1, 1])" if bad else ""))
    partial = summary.get("partial", [])
    lines.append(f"partial      {partial if partial else 'none'}"
                 + (" (left by a killed writer; delete with --delete-partial when nothing is recording)" if partial else ""))
    return "\n".join(lines)


def write_histogram_png(summary: dict[str, Any], path: Path) -> Path:
    """Bar chart of the steering histogram (plus the command shares) as a PNG; returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    edges = np.asarray(summary["steer_hist"]["edges"])
    counts = np.asarray(summary["steer_hist"]["counts"])
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 4), gridspec_kw={"width_ratios": [3, 1]})
    ax.bar((edges[:-1] + edges[1:]) / 2, counts, width=np.diff(edges) * 0.9, color="tab:blue")
    ax.set_xlim(-1, 1)
    ax.set_xlabel("steer (-1 full left, +1 full right)")
    ax.set_ylabel("frames")
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_title(f"steering: {summary['episodes']} episodes, {summary['frames']} frames, {_duration(summary['hours'])}")
    shares = summary["command_share"]
    ax2.bar(list(shares), [100 * s for s in shares.values()], color="tab:orange")
    ax2.set_ylabel("% of frames")
    ax2.set_title("commands")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path

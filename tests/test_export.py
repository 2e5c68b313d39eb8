"""Datasets other tools read: LeRobot v3 export read back by an independent reader, import-lerobot feeding
PilotNet, the Minari export, self-describing episode files, and bad input refused whole.

The independent reader is pyarrow and PyAV used directly against the v3 layout (LeRobot's own package does not
install next to this project's torch), checking every field the layout requires."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from towndrive.data.episodes import DATASET_ATTRS, FORMAT_VERSION, EpisodeError, dataset_attrs, list_episodes, read_episode

pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")
av = pytest.importorskip("av")

from towndrive.data.lerobot import LeRobotError, export_lerobot, import_lerobot  # noqa: E402

CAMERAS = {"frames": "observation.images.front", "side_left": "observation.images.side_left",
           "side_right": "observation.images.side_right"}
STATS = ("min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99")


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two short autopilot episodes with side cameras, recorded by drive.py."""
    import drive

    folder = tmp_path_factory.mktemp("episodes")
    assert drive.main(["--driver", "autopilot", "--record", str(folder), "--episodes", "2", "--seconds", "1.5",
                       "--side-cameras", "--traffic", "0", "--width", "160", "--height", "80"]) == 0
    return folder


@pytest.fixture(scope="module")
def exported(recorded: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    dst = tmp_path_factory.mktemp("lerobot") / "ds"
    done = export_lerobot(recorded, dst)
    assert done["episodes"] == 2 and done["fps"] == 20
    return dst


def _decode(path: Path) -> np.ndarray:
    with av.open(str(path)) as container:
        return np.stack([f.to_ndarray(format="rgb24") for f in container.decode(video=0)])


def test_lerobot_export_reads_back_with_pyarrow_and_pyav(recorded: Path, exported: Path) -> None:
    episodes = [read_episode(p) for p in list_episodes(recorded)]
    info = json.loads((exported / "meta" / "info.json").read_text())
    for key in ("codebase_version", "fps", "features", "total_episodes", "total_frames", "total_tasks", "chunks_size",
                "data_files_size_in_mb", "video_files_size_in_mb", "data_path", "video_path", "splits"):
        assert key in info, key
    assert info["codebase_version"] == "v3.0" and info["fps"] == 20 and isinstance(info["fps"], int)
    assert info["total_episodes"] == 2 and info["total_frames"] == sum(e.steps for e in episodes)
    features = info["features"]
    for name, dtype in (("timestamp", "float32"), ("frame_index", "int64"), ("episode_index", "int64"),
                        ("index", "int64"), ("task_index", "int64")):
        assert features[name]["dtype"] == dtype and features[name]["shape"] == [1]
    assert all("/" not in name and {"dtype", "shape", "names"} <= set(f) for name, f in features.items())
    assert features["action"]["names"] == ["steer", "throttle_brake"]
    videos = {k for k, f in features.items() if f["dtype"] == "video"}
    assert videos == set(CAMERAS.values())
    for key in videos:
        assert features[key]["shape"] == [80, 160, 3] and features[key]["info"]["video.fps"] == 20
        assert features[key]["info"]["video.codec"] == "h264"

    # Frames: every non-video feature a column of the declared type and shape, one row group per episode.
    data_file = exported / info["data_path"].format(chunk_index=0, file_index=0)
    table = pq.read_table(data_file)
    assert set(table.column_names) == {k for k in features if k not in videos}
    assert pq.ParquetFile(data_file).num_row_groups == 2
    for name in table.column_names:
        column, feature = table.schema.field(name).type, features[name]
        if feature["shape"] == [1]:
            assert column == pa.from_numpy_dtype(np.dtype(feature["dtype"])), name
        else:
            assert pa.types.is_fixed_size_list(column) and column.list_size == feature["shape"][0], name
    rows = table.to_pydict()
    assert rows["index"] == list(range(info["total_frames"]))

    # Episodes, tasks, statistics.
    eps = pq.read_table(exported / "meta" / "episodes" / "chunk-000" / "file-000.parquet").to_pylist()
    tasks = pq.read_table(exported / "meta" / "tasks.parquet").to_pydict()
    assert sorted(tasks["task_index"]) == list(range(info["total_tasks"]))
    stats = json.loads((exported / "meta" / "stats.json").read_text())
    for name, feature in features.items():
        assert set(STATS) <= set(stats[name]), name
        shape = [3, 1, 1] if feature["dtype"] == "video" else feature["shape"]
        assert list(np.shape(stats[name]["mean"])) == shape, name
    assert 0.0 <= np.min(stats["observation.images.front"]["min"]) <= np.max(stats["observation.images.front"]["max"]) <= 1.0

    decoded = {key: _decode(exported / info["video_path"].format(video_key=key, chunk_index=0, file_index=0))
               for key in videos}
    for k, (ep, row) in enumerate(zip(episodes, eps, strict=True)):
        assert row["episode_index"] == k and row["length"] == ep.steps
        start, stop = row["dataset_from_index"], row["dataset_to_index"]
        assert stop - start == ep.steps and rows["episode_index"][start:stop] == [k] * ep.steps
        assert rows["frame_index"][start:stop] == list(range(ep.steps))
        assert np.allclose(rows["timestamp"][start:stop], np.arange(ep.steps) / 20, atol=1e-6)
        assert row["tasks"][0] in tasks["task"] and ep.attrs["weather"] in row["tasks"][0]
        assert np.array_equal(np.array(rows["action"][start:stop], np.float32), ep.actions)  # the same actions
        state = np.array(rows["observation.state"][start:stop], np.float32)
        assert np.array_equal(state[:, 0], ep.speed) and np.array_equal(state[:, 1], ep.command)
        assert np.array_equal(np.array(rows["truth.route_progress_m"][start:stop], np.float32),
                              ep.truth["route_progress_m"])
        for name, key in CAMERAS.items():
            first = round(row[f"videos/{key}/from_timestamp"] * 20)
            assert round(row[f"videos/{key}/to_timestamp"] * 20) - first == ep.steps
            frames = decoded[key][first:first + ep.steps]
            original = ep.frames if name == "frames" else ep.extras[name]
            assert frames.shape == original.shape  # the same number of frames per episode
            error = frames.astype(np.float64) - original
            psnr = 10 * np.log10(255**2 / np.mean(error**2))  # yuv420p halves the colour resolution: about 30 dB here
            assert np.abs(error).mean() < 4.0 and psnr > 28.0, (key, np.abs(error).mean(), psnr)
    assert sum(len(v) for v in decoded.values()) == 3 * info["total_frames"]


def test_import_lerobot_trains_pilotnet(exported: Path, recorded: Path, tmp_path: Path) -> None:
    import train

    paths = import_lerobot(exported, tmp_path / "imported")
    originals = [read_episode(p) for p in list_episodes(recorded)]
    assert len(paths) == 2
    for path, original in zip(paths, originals, strict=True):
        ep = read_episode(path)
        assert np.array_equal(ep.actions, original.actions) and np.array_equal(ep.command, original.command)
        assert ep.frames.shape == original.frames.shape and ep.attrs["town_seed"] == original.attrs["town_seed"]
        assert np.abs(ep.frames.astype(np.int16) - original.frames).mean() < 4.0
    out = tmp_path / "run"
    assert train.main(["pilotnet", "--data", str(tmp_path / "imported"), "--out", str(out), "--model", str(out / "m.pt"),
                       "--epochs", "1", "--samples-per-epoch", "32", "--batch", "16", "--threads", "1",
                       "--validation", "0.5", "--seed", "3"]) == 0
    assert (out / "m.pt").exists()


def test_minari_export_loads_and_iterates(recorded: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    minari = pytest.importorskip("minari")
    from towndrive.data.minari_export import MinariExportError, export_minari

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    export_minari(recorded, "towndrive/test-v0")
    dataset = minari.load_dataset("towndrive/test-v0")
    originals = [read_episode(p) for p in list_episodes(recorded)]
    assert dataset.total_episodes == 2
    assert dataset.observation_space["image"].shape == (80, 160, 3) and "side" in dataset.observation_space.spaces
    for ep, original in zip(dataset.iterate_episodes(), originals, strict=True):
        assert np.array_equal(ep.observations["image"], original.frames)  # lossless
        assert np.array_equal(ep.actions, original.actions[:-1]) and ep.truncations[-1]
    with pytest.raises(MinariExportError, match="already exists"):
        export_minari(recorded, "towndrive/test-v0")


def test_every_dataset_describes_itself_and_version_1_files_still_open(recorded: Path, tmp_path: Path) -> None:
    path = list_episodes(recorded)[0]
    with h5py.File(path, "r") as f:
        assert f.attrs["format_version"] == FORMAT_VERSION == 2
        names: list[str] = []
        f.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset) else None)
        for name in names:
            assert {"unit", "dims", "description"} <= set(f[name].attrs), name
        assert f["speed"].attrs["unit"] == "m/s"
        assert json.loads(f["command"].attrs["codes"]) == {"0": "follow", "1": "left", "2": "right", "3": "straight"}
        assert json.loads(f["truth/next_light_state"].attrs["codes"])["2"] == "red"
    old = tmp_path / "episode_00000.h5"  # the version 1 layout: bare datasets
    with h5py.File(old, "w") as f:
        f.attrs["format_version"] = 1
        f["frames"] = np.zeros((3, 4, 6, 3), np.uint8)
        f["actions"] = np.zeros((3, 2), np.float32)
        f["speed"] = np.ones(3, np.float32)
        f["command"] = np.zeros(3, np.int8)
        f["truth/time_s"] = np.arange(3, dtype=np.float32)
    ep = read_episode(old)
    assert ep.steps == 3 and ep.frames.shape == (3, 4, 6, 3)
    described = dataset_attrs(old)
    assert described["speed"] == DATASET_ATTRS["speed"] and described["truth/time_s"]["unit"] == "s"


def _leftovers(parent: Path) -> list[Path]:
    return [p for p in parent.iterdir() if p.name.endswith(".partial")]


def test_bad_input_is_one_sentence_and_leaves_nothing(recorded: Path, exported: Path, tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    from towndrive.data.__main__ import main as data

    broken = tmp_path / "broken"
    broken.mkdir()
    for p in list_episodes(recorded):
        (broken / p.name).write_bytes(p.read_bytes())
    bad = broken / "episode_00001.h5"
    bad.write_bytes(bad.read_bytes()[: bad.stat().st_size // 2])  # cut short: a corrupt episode
    out = tmp_path / "out"
    with pytest.raises(EpisodeError, match="episode_00001.h5"):
        export_lerobot(broken, out)
    assert not out.exists() and not _leftovers(tmp_path)

    assert data(["export-lerobot", str(recorded), str(exported)]) == 2  # a destination that is not empty
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "not empty" in err and err.count("\n") == 0

    lacking = tmp_path / "lacking"  # a dataset whose action does not name steering and throttle
    (lacking / "meta").mkdir(parents=True)
    info = json.loads((exported / "meta" / "info.json").read_text())
    info["features"]["action"]["names"] = ["joint_1", "joint_2"]
    (lacking / "meta" / "info.json").write_text(json.dumps(info))
    with pytest.raises(LeRobotError, match="steering"):
        import_lerobot(lacking, tmp_path / "imported")
    assert not (tmp_path / "imported").exists() and not _leftovers(tmp_path)


def test_a_missing_extra_is_named(recorded: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    from towndrive.data.__main__ import main as data

    for name in [m for m in sys.modules if m == "pyarrow" or m.startswith("pyarrow.")]:
        monkeypatch.setitem(sys.modules, name, None)
    assert data(["export-lerobot", str(recorded), str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "pip install 'towndrive[dataset]'" in err and not (tmp_path / "out").exists()

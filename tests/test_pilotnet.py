"""PilotNet: the paper's architecture, the shared preprocessing, label geometry, data handling, training,
export and the driver."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from towndrive.agent.perception.pilotnet import ConditionalPilotNet, PilotNet, build, parameter_count, preprocess, to_tensor
from towndrive.agent.training.pilotnet_data import (
    MIRRORED_COMMAND,
    Augment,
    Augmenter,
    FrameSet,
    ViewpointWarp,
    balance_weights,
    corrected_steer,
    split_by_episode,
)
from towndrive.sim.render import CameraConfig


def test_pilotnet_has_the_papers_layers_and_parameter_count():
    model = PilotNet()
    # conv 24, 36, 48 (5x5, stride 2), 64, 64 (3x3); fc 100, 50, 10, 1; no 1164-unit layer
    convs = [m for m in model.modules() if isinstance(m, torch.nn.Conv2d)]
    assert [(c.out_channels, c.kernel_size, c.stride) for c in convs] == [
        (24, (5, 5), (2, 2)), (36, (5, 5), (2, 2)), (48, (5, 5), (2, 2)), (64, (3, 3), (1, 1)), (64, (3, 3), (1, 1))]
    fcs = [m for m in model.modules() if isinstance(m, torch.nn.Linear)]
    assert [(f.in_features, f.out_features) for f in fcs] == [(1152, 100), (100, 50), (50, 10), (10, 1)]
    assert parameter_count(model) == 252_219
    assert model(torch.zeros(2, 3, 66, 200)).shape == (2, 1)


def test_conditional_variant_selects_a_branch_per_command():
    torch.manual_seed(0)
    model = ConditionalPilotNet().eval()
    x = torch.rand(1, 3, 66, 200).repeat(4, 1, 1, 1) * 255
    out = model(x, torch.arange(4))[:, 0]
    assert len(set(out.tolist())) == 4  # same image, four commands, four different branches
    assert parameter_count(model) < 300_000


def test_normalisation_is_fixed_inside_the_network():
    model = PilotNet()
    assert not any(p.requires_grad for p in model.features[0].parameters())
    assert float(model.features[0](torch.tensor([0.0, 255.0]))[0]) == pytest.approx(-1.0)


def test_preprocess_crops_resizes_and_converts_to_yuv():
    rgb = np.zeros((160, 320, 3), np.uint8)
    rgb[:64] = (0, 0, 255)  # "sky": blue above the crop line
    rgb[64:] = (255, 0, 0)  # red road
    yuv = preprocess(rgb)
    assert yuv.shape == (66, 200, 3) and yuv.dtype == np.uint8
    # everything kept is the red part: Y of pure red is about 76, V (Cr) high
    assert abs(int(yuv[..., 0].mean()) - 76) <= 2 and yuv[..., 2].min() > 200
    assert to_tensor(yuv).shape == (1, 3, 66, 200)
    with pytest.raises(ValueError, match="uint8 RGB"):
        preprocess(rgb.astype(np.float32))


def test_corrected_steer_brings_the_car_back_in_two_seconds():
    # shifted right (positive) -> steer left (more negative); turned right -> steer left too
    assert corrected_steer(0.0, 0.5, 0.0, 8.0) < 0 < corrected_steer(0.0, -0.5, 0.0, 8.0)
    assert corrected_steer(0.0, 0.0, 0.05, 8.0) < 0
    assert corrected_steer(0.2, 0.0, 0.0, 8.0) == pytest.approx(0.2, abs=1e-6)
    # arc geometry: the offset closes over 16 m: curvature 2 x 0.5 / 16^2, wheel angle atan(k x 4.6)
    expected = -np.arctan(2 * 0.5 / 16.0**2 * 4.6) / 0.6
    assert corrected_steer(0.0, 0.5, 0.0, 8.0) == pytest.approx(expected, rel=1e-5)


def test_viewpoint_warp_reproduces_a_side_camera(town):
    """The flat-world re-projection of the centre frame matches a camera really rendered 0.6 m to the side."""
    from towndrive.sim.render import SceneRenderer

    renderer = SceneRenderer(town, seed=town.seed)
    try:
        x, y, heading = _pose_on_a_lane(town)
        cam = CameraConfig()
        centre = preprocess(renderer.render((x, y, heading), cam).rgb)
        side = preprocess(renderer.render((x, y, heading), cam, lateral_m=0.6).rgb)
    finally:
        renderer.close()
    warped = ViewpointWarp(cam)(centre, 0.6, 0.0)
    road = slice(30, 66)  # the ground part of the image, where the flat-world model holds
    err_warped = np.abs(warped[road].astype(int) - side[road]).mean()
    err_plain = np.abs(centre[road].astype(int) - side[road]).mean()
    assert err_warped < 2.0 and err_warped < 0.2 * err_plain


def _pose_on_a_lane(town) -> tuple[float, float, float]:
    lane = next(town.lane(index) for index in town.road_lanes() if town.lane(index).length > 60)
    pos = lane.position(20.0, 0.0)
    return float(pos[0]), float(pos[1]), float(lane.heading_at(20.0))


def test_augmenter_flips_mirror_the_command_and_negate_steering():
    rng = np.random.default_rng(0)
    img = np.random.default_rng(1).integers(0, 255, (66, 200, 3), dtype=np.uint8)
    aug = Augmenter(CameraConfig(), Augment(viewpoint_p=0.0, flip_p=1.0, brightness=(1.0, 1.0), shadow_p=0.0))
    out, steer, command = aug(rng, img, 0.3, 8.0, 1)
    assert steer == pytest.approx(-0.3) and command == 2 and np.array_equal(out, img[:, ::-1])
    assert list(MIRRORED_COMMAND) == [0, 2, 1, 3]


def test_balancing_flattens_the_steering_histogram():
    rng = np.random.default_rng(0)
    steer = np.concatenate([rng.normal(0, 0.02, 9000), rng.uniform(-0.8, 0.8, 1000)]).astype(np.float32)
    w = balance_weights(steer)
    straight = np.abs(steer) < 0.05
    assert straight.mean() > 0.85 and w[straight].sum() < 0.5


def test_split_is_by_episode():
    n = 40
    frames = FrameSet(np.zeros((n, 66, 200, 3), np.uint8), np.zeros(n, np.float32), np.ones(n, np.float32),
                      np.zeros(n, np.int64), np.repeat(np.arange(8), 5), [None] * 8)  # type: ignore[list-item]
    train, val = split_by_episode(frames, 0.25, seed=3)
    assert len(val) == 10 and not set(train.episode) & set(val.episode)


def test_onnx_export_matches_torch(tmp_path):
    from towndrive.agent.training.pilotnet_training import export, load_model

    torch.manual_seed(0)
    model = build(conditional=True).eval()
    diff = export(model, {"conditional": True, "crop": {"top": 0.4, "bottom": 1.0}}, tmp_path / "p.pt")
    assert diff <= 1e-4
    loaded, meta = load_model(tmp_path / "p.pt")
    assert meta["conditional"] is True
    x = torch.rand(2, 3, 66, 200) * 255
    c = torch.tensor([1, 3])
    assert torch.equal(loaded(x, c), model(x, c))


def test_loading_a_wrong_file_is_one_clear_error(tmp_path):
    from towndrive.agent.training.pilotnet_training import load_model

    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="bad.pt is not a PilotNet checkpoint"):
        load_model(bad)
    with pytest.raises(FileNotFoundError, match="train one with"):
        load_model(tmp_path / "missing.pt")


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    """Two short autopilot episodes with side cameras, recorded by drive.py."""
    import drive

    folder = tmp_path_factory.mktemp("episodes")
    assert drive.main(["--driver", "autopilot", "--record", str(folder), "--episodes", "2", "--seconds", "4",
                       "--side-cameras", "--noise",
                       "--traffic", "0", "--width", "160", "--height", "80"]) == 0
    return folder


def test_side_cameras_load_with_corrected_labels(tiny_dataset):
    from towndrive.agent.training.pilotnet_data import load_frames

    with_side = load_frames([tiny_dataset])
    centre = load_frames([tiny_dataset], side_cameras=False)
    assert len(with_side) == 3 * len(centre) > 0
    first = with_side.steer[with_side.episode == 0].reshape(3, -1)  # centre, left camera, right camera
    assert np.all(first[1] > first[0]) and np.all(first[2] < first[0])  # left camera steers right, and vice versa


def test_episodes_loaded_by_worker_processes_are_the_ones_loaded_here(tiny_dataset):
    from towndrive.agent.training.pilotnet_data import load_frames

    here, there = load_frames([tiny_dataset]), load_frames([tiny_dataset], workers=2)
    assert len(here) > 0 and there.episode_paths == here.episode_paths
    for name in ("images", "steer", "speed", "command", "episode"):
        assert np.array_equal(getattr(here, name), getattr(there, name)), name


def _train(folder, out, *extra):
    import train

    return train.main(["pilotnet", "--data", str(folder), "--out", str(out), "--model", str(out / "m.pt"),
                       "--samples-per-epoch", "96", "--batch", "32", "--threads", "1", "--validation", "0.5",
                       "--seed", "7", *extra])


def test_training_is_deterministic_resumable_and_exports(tiny_dataset, tmp_path):
    from towndrive.agent.training.pilotnet_training import load_model

    assert _train(tiny_dataset, tmp_path / "a", "--epochs", "2") == 0
    assert _train(tiny_dataset, tmp_path / "b", "--epochs", "1") == 0
    assert _train(tiny_dataset, tmp_path / "b", "--epochs", "2", "--resume") == 0
    a, _ = load_model(tmp_path / "a" / "last.pt")
    b, _ = load_model(tmp_path / "b" / "last.pt")
    for (name, pa), (_, pb) in zip(a.state_dict().items(), b.state_dict().items(), strict=True):
        assert torch.equal(pa, pb), name
    for name in ("log.csv", "loss.png", "best.pt", "m.onnx", "summary.json"):
        assert (tmp_path / "a" / name).exists() or (tmp_path / "a" / "m.onnx").exists(), name
    rows = (tmp_path / "b" / "log.csv").read_text().strip().splitlines()
    assert len(rows) == 3  # header + two epochs, across the resume


def test_dagger_round_records_learner_episodes_labelled_by_the_autopilot(tiny_dataset, tmp_path):
    from towndrive.data.episodes import list_episodes, read_episode

    assert _train(tiny_dataset, tmp_path, "--epochs", "1", "--dagger", "1", "--dagger-episodes", "1",
                  "--dagger-seconds", "3", "--dagger-epochs", "1") == 0
    episodes = list_episodes(tmp_path / "dagger" / "round_1")
    assert len(episodes) == 1
    ep = read_episode(episodes[0], load_frames=False)
    assert ep.attrs["driver"] == "dagger" and ep.steps == 60
    rows = (tmp_path / "log.csv").read_text().strip().splitlines()
    assert len(rows) == 3  # header, the base epoch, the DAgger epoch


def test_training_on_a_missing_folder_is_one_clear_error(tmp_path, capsys):
    assert _train(tmp_path / "nothing", tmp_path / "out", "--epochs", "1") == 2
    assert "no such dataset folder" in capsys.readouterr().err


def test_shipped_model_keeps_its_lane_closed_loop_in_an_unseen_town():
    """The shipped PilotNet drives 25 s of a route in a town never used for training, without the safety driver."""
    from dataclasses import replace

    from towndrive.agent.drivers import make_driver
    from towndrive.envs.drive_env import DriveConfig, DriveEnv
    from towndrive.envs.evaluation import run_episode
    from towndrive.envs.metrics import episode_metrics
    from towndrive.sim.world import WorldConfig

    world = replace(WorldConfig(), npc_count=0, pedestrian_count=0)
    env = DriveEnv(DriveConfig(world=world, max_time_s=25.0, terminate_on_infraction=False,
                               terminate_on_route_deviation=False))
    try:
        trace = run_episode(env, make_driver("pilotnet"), seed=512, options={"town_seed": 103, "weather": "dusk"})
    finally:
        env.close()
    m = episode_metrics(trace)
    assert m["interventions"] == 0, m
    assert m["mean_abs_lane_offset_m"] < 0.4 and trace.route_progress_m > 100.0, m


def test_driver_uses_only_the_camera_speed_and_command():
    from towndrive.agent.drivers import make_driver

    driver = make_driver("pilotnet", backend="torch")
    assert driver.privileged is False
    frame = np.zeros((160, 320, 3), np.uint8)
    action = driver.act({"image": frame, "speed": np.array([3.0], np.float32), "command": 1})
    assert action.shape == (2,) and np.all(np.abs(action) <= 1.0) and action[1] > 0  # below target speed: throttle

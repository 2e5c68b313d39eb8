"""Deployment profiles: where and how the agent runs, as one YAML file per target.

A profile says, per model (``pilotnet``, ``detector``), the inference backend (``torch``, ``onnxruntime``,
``tensorrt``), the precision (``fp32``, ``fp16``, ``int8``) and the input size; per module, how often it
runs (the detector every k frames with SORT predicting in between, as seed 000 did; stereo every m frames)
and whether the detector's second stages (the pedestrian refiner, the sign reader) run after it; a latency budget
per stage; the camera source; and the alert output. The shipped profiles live in
``agent/deploy/profiles/``: ``cpu`` (the default, runs here), ``jetson-nano``, ``jetson-xavier``, ``jetson-orin``.

Why so strict: a profile is edited by hand on a car, and a misspelt key (``precison: int8``) that is
silently ignored would run fp32 and report the wrong latency. Every unknown key or value is one
``ProfileError`` that names the file and the key. Keys left out take the dataclass defaults below, so an
empty file is the CPU profile. Relative paths are relative to the repository root.

The agent driver takes a ``Profile`` (``load_profile("cpu")``) and asks it for its models
(``agent.deploy.backends.open_pilotnet(profile)``, ``open_detector(profile)``), its module rates
(``profile.every("detector")``), its camera geometry (``profile.camera_config()``) and its budgets.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, get_type_hints

from towndrive.agent.shipped import ROOT
from towndrive.sim.spec import ROAD, CrossStreetOdds, RoadDesign, SignalMount, TurnRadius, TurnReach

PROFILE_DIR = Path(__file__).resolve().parent / "profiles"

BACKENDS = ("torch", "onnxruntime", "tensorrt")
PRECISIONS = ("fp32", "fp16", "int8")
MODELS = ("pilotnet", "detector")
MODULES = ("detector", "refiner", "sign_reader", "lanes", "stop_line", "stereo")
SECOND_STAGES = ("refiner", "sign_reader")  # run on the detector's boxes whenever it runs: only enabled is theirs to set
# The agent driver's stages (agent.agent_driver: distance includes stereo matching, which agent.deploy.profiled_agent times
# apart as "stereo"), plus reading the camera and sending alerts.
STAGES = ("camera", "pilotnet", "detector", "tracking", "lanes", "stop_line", "stereo", "distance", "control", "adas",
          "alerts", "total")
SOURCES = ("simulator", "video", "usb", "csi", "episode")
STEREO_LAYOUTS = ("none", "side-by-side", "simulator")
# The precisions each backend can run (torch stays the fp32 reference; int8 is calibrated on recorded frames:
# ONNX Runtime runs a statically quantized QDQ model, TensorRT builds with a calibration cache).
BACKEND_PRECISIONS = {"torch": ("fp32",), "onnxruntime": ("fp32", "fp16", "int8"), "tensorrt": ("fp32", "fp16", "int8")}
PILOTNET_INPUT = (200, 66)  # width, height: fixed by the network's flatten layer


class ProfileError(ValueError):
    """A profile that cannot be used; the message names the file and the key."""


@dataclass(frozen=True)
class ModelProfile:
    """One network: which file, which runtime, which arithmetic, which input size (width, height)."""

    checkpoint: str = ""  # the torch checkpoint: source of every export and the torch backend
    backend: str = "onnxruntime"
    precision: str = "fp32"
    input_size: tuple[int, int] = (0, 0)  # width, height
    threads: int = 1  # CPU threads for torch / ONNX Runtime
    dla_core: int | None = None  # TensorRT: run on this DLA core (Xavier, Orin), GPU fallback allowed
    workspace_mb: int = 1024  # TensorRT builder memory pool


@dataclass(frozen=True)
class ModuleProfile:
    """How often one perception module runs: every ``every`` frames (1 = every frame)."""

    enabled: bool = True
    every: int = 1


@dataclass(frozen=True)
class CameraProfile:
    """Where frames come from and the camera's geometry (lanes and stop-line distances need it)."""

    source: str = "simulator"
    path: str | None = None  # video or episode file (source video / episode)
    device: int = 0  # USB camera index (/dev/videoN)
    sensor_id: int = 0  # CSI camera (nvarguscamerasrc sensor-id)
    capture_width: int = 1280  # what the camera delivers (usb, csi); side-by-side: both eyes together
    capture_height: int = 720
    fps: int = 30
    flip_method: int = 0  # nvvidconv flip-method (0-7) for a CSI camera mounted upside down (2)
    stereo: str = "none"  # none, side-by-side (ZED-style left|right in one frame), simulator
    width: int = 320  # the frame size the agent works at (frames are centre-cropped to its aspect, resized)
    height: int = 160
    hfov_deg: float = 90.0  # horizontal field of view of the delivered frame (one eye), before cropping
    mount_height_m: float = 1.3
    pitch_deg: float = -4.0
    stereo_baseline_m: float = 0.12  # ZED: 0.12 m


@dataclass(frozen=True)
class AlertProfile:
    """Where each frame's decision goes: a serial port (microcontroller) and/or a JSON-lines file."""

    serial_port: str | None = None  # e.g. /dev/ttyACM0 (TIVA LaunchPad), /dev/ttyTHS0 (Jetson UART)
    baud: int = 115200
    jsonl: str | None = None  # a path, or "-" for standard output


def _default_models() -> dict[str, ModelProfile]:
    return {"pilotnet": ModelProfile("data/models/pilotnet.pt", input_size=PILOTNET_INPUT),
            "detector": ModelProfile("data/models/detector_signs.pt", input_size=(320, 160))}  # the agent's default


def _default_modules() -> dict[str, ModuleProfile]:
    # refiner: the pedestrian refiner after the detector (data/models/ped_refiner.onnx, ONNX Runtime on the CPU);
    # sign_reader: reads which sign each sign box holds (data/models/sign_reader.onnx, likewise), as the agent does
    return {"detector": ModuleProfile(), "refiner": ModuleProfile(), "sign_reader": ModuleProfile(),
            "lanes": ModuleProfile(), "stop_line": ModuleProfile(), "stereo": ModuleProfile(enabled=False)}


@dataclass(frozen=True)
class Profile:
    """A deployment target (see module docstring). Build with ``load_profile``; all fields have working defaults."""

    name: str = "cpu"
    description: str = ""
    export_dir: str = "out/deploy/{name}"  # where train.py export writes ONNX files, calibration and scripts
    models: dict[str, ModelProfile] = field(default_factory=_default_models)
    modules: dict[str, ModuleProfile] = field(default_factory=_default_modules)
    budgets_ms: dict[str, float] = field(default_factory=dict)
    camera: CameraProfile = field(default_factory=CameraProfile)
    alerts: AlertProfile = field(default_factory=AlertProfile)
    road: RoadDesign = ROAD  # the road-design priors the agent assumes (sim.spec): a country's roads may differ
    source_file: str = "<defaults>"

    # ------------------------------------------------------------------ queries the agent uses
    def every(self, module: str) -> int:
        """Run ``module`` on every k-th frame; 0 when the profile turns it off."""
        m = self.modules[module]
        return m.every if m.enabled else 0

    def budget_ms(self, stage: str) -> float | None:
        return self.budgets_ms.get(stage)

    @property
    def export_path(self) -> Path:
        return resolve(self.export_dir.format(name=self.name))

    def model_file(self, model: str) -> Path:
        """The file the model's backend loads: the .pt (torch), an .onnx (onnxruntime) or an .engine (tensorrt).

        ONNX Runtime at fp32 falls back to the ONNX twin shipped beside the checkpoint, so the CPU profile
        runs without an export step.
        """
        spec = self.models[model]
        checkpoint = resolve(spec.checkpoint)
        if spec.backend == "torch":
            return checkpoint
        if spec.backend == "onnxruntime":
            exported = self.export_path / f"{model}.{spec.precision}.onnx"
            if spec.precision == "fp32" and not exported.exists() and checkpoint.with_suffix(".onnx").exists():
                return checkpoint.with_suffix(".onnx")
            return exported
        return self.export_path / f"{model}.{spec.precision}.engine"

    def camera_config(self, eye_size: tuple[int, int] | None = None) -> Any:
        """The ``sim.render.CameraConfig`` of the frames the agent sees (after the source's crop and resize).

        ``eye_size`` is the delivered frame's (width, height) per eye (default: the profile's capture size).
        A frame wider than the agent's aspect is centre-cropped, which narrows the field of view:
        ``tan(hfov'/2) = (crop share) tan(hfov/2)``.
        """
        from towndrive.sim.render import CameraConfig

        c = self.camera
        hfov = c.hfov_deg
        if c.source != "simulator":
            eye_w, eye_h = eye_size or (c.capture_width / (2 if c.stereo == "side-by-side" else 1), c.capture_height)
            share = min(1.0, (eye_h * c.width / c.height) / eye_w)
            hfov = math.degrees(2 * math.atan(share * math.tan(math.radians(hfov) / 2)))
        return CameraConfig(width=c.width, height=c.height, hfov_deg=hfov, mount_height_m=c.mount_height_m,
                            pitch_deg=c.pitch_deg, stereo=c.stereo != "none", stereo_baseline_m=c.stereo_baseline_m)

    def with_camera(self, **changes: Any) -> Profile:
        """The same profile with some camera fields changed (``drive.py --camera`` uses it), validated again."""
        p = replace(self, camera=replace(self.camera, **changes))
        p.validate()
        return p

    # ------------------------------------------------------------------ validation
    def validate(self) -> None:
        """Cross-field rules; raises ``ProfileError`` naming the file and the key."""
        f = self.source_file
        for name, m in self.models.items():
            key = f"models.{name}"
            if m.precision not in BACKEND_PRECISIONS[m.backend]:
                hint = "fp16 and int8 run on onnxruntime or tensorrt; torch is the fp32 reference"
                raise ProfileError(f"{f}: {key}.precision {m.precision!r} cannot run on backend {m.backend!r}: {hint}.")
            if not m.checkpoint:
                raise ProfileError(f"{f}: {key}.checkpoint is empty; name the model's .pt file.")
            w, h = m.input_size
            if name == "pilotnet" and (w, h) != PILOTNET_INPUT:
                raise ProfileError(f"{f}: {key}.input_size must be {list(PILOTNET_INPUT)} (PilotNet's layers fix it), "
                                   f"not {[w, h]}.")
            if name == "detector" and (w <= 0 or h <= 0 or w % 16 or h % 16):
                raise ProfileError(f"{f}: {key}.input_size {[w, h]} must be positive multiples of 16 (the detector's "
                                   "coarsest stride).")
            if m.threads < 0 or m.workspace_mb <= 0 or (m.dla_core is not None and m.dla_core < 0):
                raise ProfileError(f"{f}: {key}: threads >= 0, workspace_mb > 0 and dla_core >= 0 (or null).")
            if m.dla_core is not None and m.backend != "tensorrt":
                raise ProfileError(f"{f}: {key}.dla_core is for the tensorrt backend only.")
        for name, mod in self.modules.items():
            if mod.every < 1:
                raise ProfileError(f"{f}: modules.{name}.every must be 1 or more (frames between runs), not {mod.every}.")
            if name in SECOND_STAGES and mod.every != 1:  # it would be ignored: a second stage runs with the detector
                raise ProfileError(f"{f}: modules.{name}.every must be 1, since it runs on the detector's boxes whenever "
                                   "the detector runs; set modules.detector.every instead.")
        for stage, ms in self.budgets_ms.items():
            if not ms > 0:
                raise ProfileError(f"{f}: budgets_ms.{stage} must be a positive number of milliseconds, not {ms}.")
        c = self.camera
        if c.source in ("video", "episode") and not c.path:
            raise ProfileError(f"{f}: camera.path is needed for camera.source {c.source!r}.")
        if c.stereo == "side-by-side" and c.source not in ("video", "usb", "csi"):
            raise ProfileError(f"{f}: camera.stereo 'side-by-side' is for video, usb or csi sources, not {c.source!r}.")
        if c.stereo == "simulator" and c.source != "simulator":
            raise ProfileError(f"{f}: camera.stereo 'simulator' needs camera.source 'simulator'.")
        if self.every("stereo") and c.stereo == "none":
            raise ProfileError(f"{f}: modules.stereo is enabled but camera.stereo is 'none'; set camera.stereo or "
                               "disable modules.stereo.")
        for key in ("width", "height", "capture_width", "capture_height", "fps"):
            if getattr(c, key) <= 0:
                raise ProfileError(f"{f}: camera.{key} must be positive.")
        if not 0 < c.hfov_deg < 180:
            raise ProfileError(f"{f}: camera.hfov_deg must be between 0 and 180 degrees.")
        if self.alerts.baud <= 0:
            raise ProfileError(f"{f}: alerts.baud must be positive.")


# ---------------------------------------------------------------------- loading
def resolve(path: str | Path) -> Path:
    """A profile path: absolute as given; a relative one from the current directory, or, when nothing is there, a
    file shipped with the package (``data/models/...``: the shipped models, wherever the package is installed)."""
    p = Path(path).expanduser()
    if p.is_absolute():
        return p
    here = Path.cwd() / p
    shipped = ROOT / p
    return shipped if shipped.exists() and not here.exists() else here


def available_profiles() -> list[str]:
    return sorted(p.stem for p in PROFILE_DIR.glob("*.yaml"))


def load_profile(name_or_path: str | Path = "cpu") -> Profile:
    """A shipped profile by name (``cpu``, ``jetson-xavier`` ...) or any YAML file by path."""
    path = Path(name_or_path)
    if path.suffix not in (".yaml", ".yml"):
        path = PROFILE_DIR / f"{name_or_path}.yaml"
        if not path.is_file():
            raise ProfileError(f"Unknown profile {str(name_or_path)!r}; choose one of {', '.join(available_profiles())}, "
                               "or give the path of a .yaml file.")
    if not path.is_file():
        raise ProfileError(f"Profile file {path} not found.")
    import yaml

    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except UnicodeDecodeError as exc:
        raise ProfileError(f"{path}: not UTF-8 text (byte {exc.object[exc.start]:#x} at offset {exc.start}); "
                           "save the profile as UTF-8.") from None
    except yaml.YAMLError as exc:
        raise ProfileError(f"{path}: not valid YAML ({exc}).") from exc
    return profile_from_dict(data, str(path), default_name=path.stem)


def profile_from_dict(data: Any, source: str = "<dict>", default_name: str = "cpu") -> Profile:
    """Build and validate a profile from parsed YAML; unknown keys and values are ``ProfileError``s."""
    if not isinstance(data, dict):
        raise ProfileError(f"{source}: a profile is a mapping of keys (name, models, modules, ...), not {type(data).__name__}.")
    data = dict(data)
    top_keys = [f.name for f in fields(Profile) if f.name != "source_file"]
    unknown = [k for k in data if k not in top_keys]
    if unknown:  # checked here, where every top-level key is known (nested sections are popped below)
        raise ProfileError(f"{source}: unknown key '{unknown[0]}'; known keys here: {', '.join(top_keys)}.")
    models = _default_models()
    for name, spec in _mapping(data.pop("models", {}), source, "models").items():
        if name not in MODELS:
            raise ProfileError(f"{source}: unknown key 'models.{name}'; known models: {', '.join(MODELS)}.")
        models[name] = _build(ModelProfile, spec, source, f"models.{name}", models[name])
    modules = _default_modules()
    for name, spec in _mapping(data.pop("modules", {}), source, "modules").items():
        if name not in MODULES:
            raise ProfileError(f"{source}: unknown key 'modules.{name}'; known modules: {', '.join(MODULES)}.")
        modules[name] = _build(ModuleProfile, spec, source, f"modules.{name}", modules[name])
    budgets: dict[str, float] = {}
    for stage, ms in _mapping(data.pop("budgets_ms", {}), source, "budgets_ms").items():
        if stage not in STAGES:
            raise ProfileError(f"{source}: unknown key 'budgets_ms.{stage}'; known stages: {', '.join(STAGES)}.")
        budgets[stage] = _value(float, ms, source, f"budgets_ms.{stage}")
    camera = _build(CameraProfile, data.pop("camera", {}), source, "camera", CameraProfile())
    alerts = _build(AlertProfile, data.pop("alerts", {}), source, "alerts", AlertProfile())
    try:
        road_data = dict(_mapping(data.pop("road", {}), source, "road"))
        lists = {key: road_data.pop(key) for key in _ROAD_LISTS if key in road_data}
        road = _build(RoadDesign, road_data, source, "road", ROAD)
        for key, items in lists.items():
            base = _ROAD_LISTS[key]
            if not isinstance(items, list):
                names = ", ".join(f.name for f in fields(base))
                raise ProfileError(f"{source}: road.{key} must be a list of {{{names}}}, not {items!r}.")
            road = replace(road, **{key: tuple(_build(type(base), item, source, f"road.{key}[{k}]", base)
                                               for k, item in enumerate(items))})
    except ProfileError:
        raise
    except ValueError as exc:  # a prior outside real roads' range (RoadDesign checks its own)
        raise ProfileError(f"{source}: {exc}") from None
    data.setdefault("name", default_name)
    top = _build(Profile, data, source, "", Profile(), skip=("models", "modules", "budgets_ms", "camera", "alerts", "road",
                                                            "source_file"))
    profile = replace(top, models=models, modules=modules, budgets_ms=budgets, camera=camera, alerts=alerts, road=road,
                      source_file=source)
    profile.validate()
    return profile


# The road design's lists: each item a mapping of the item's fields, the keys left out taken from these.
_ROAD_LISTS: dict[str, Any] = {
    "other_signal_mounts": SignalMount(0.0, 0.0, ROAD.signal_head_height_m),
    "turn_reaches": TurnReach(1, 15.0, 10.0),
    "right_turn_radii": TurnRadius(1, 1, 10.0),
    "cross_street_odds": CrossStreetOdds("signal", 1, 0.5, 1),
}

_CHOICES = {"backend": BACKENDS, "precision": PRECISIONS, "source": SOURCES, "stereo": STEREO_LAYOUTS}


def _mapping(value: Any, source: str, key: str) -> dict[str, Any]:
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise ProfileError(f"{source}: '{key}' must be a mapping, not {type(value).__name__}.")
    return value


def _build(cls: type, data: Any, source: str, where: str, base: Any, skip: tuple[str, ...] = ()) -> Any:
    """``base`` with the keys of ``data`` replaced, each checked against the dataclass field's type and choices."""
    data = _mapping(data, source, where or "profile")
    hints = get_type_hints(cls)
    known = [f.name for f in fields(cls) if f.name not in skip]
    changes = {}
    for key, value in data.items():
        full = f"{where}.{key}" if where else str(key)
        if key not in known:
            raise ProfileError(f"{source}: unknown key '{full}'; known keys here: {', '.join(known)}.")
        checked = _value(hints[key], value, source, full)
        if key in _CHOICES and checked not in _CHOICES[key]:
            raise ProfileError(f"{source}: {full} is {value!r}; use one of {', '.join(_CHOICES[key])}.")
        changes[key] = checked
    return replace(base, **changes)


def _value(hint: Any, value: Any, source: str, key: str) -> Any:
    """One YAML value checked against a field type: str, int, float, bool, optional, (int, int)."""
    text = str(hint)
    optional = "None" in text
    if value is None:
        if optional:
            return None
        raise ProfileError(f"{source}: {key} cannot be empty.")
    if hint in (str, "str") or text.startswith("str"):
        if isinstance(value, str):
            return value
    elif hint is bool:
        if isinstance(value, bool):
            return value
    elif hint is int or text.startswith("int"):
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif hint is float or text.startswith("float"):
        if isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value):
            return float(value)
    elif text.startswith("tuple"):
        if (isinstance(value, list | tuple) and len(value) == 2
                and all(isinstance(v, int) and not isinstance(v, bool) for v in value)):
            return (int(value[0]), int(value[1]))
        raise ProfileError(f"{source}: {key} must be [width, height] in pixels, not {value!r}.")
    kind = {bool: "true or false", int: "an integer", float: "a number"}.get(hint, "text")
    raise ProfileError(f"{source}: {key} must be {kind}, not {value!r}.")

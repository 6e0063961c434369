"""dapm-lightning collect-carla: the paper's UAPD acquisition loop against a CARLA server.

Paper §"Data Acquisition": towns without Town02, weather ClearNoon with the hour drawn from 8-17,
200 vehicles and 200 walkers after each reset, camera in a 100 x 100 m square around the origin,
height / pitch / roll / yaw / FoV and the lens distortion drawn per the paper's parameter table,
RGB and depth images, depth log-encoded to 8 bits (Eq. 20), UAPD naming, a 200 ms pause after each
sample. Every sample's parameters depend only on (seed, index), so an interrupted run resumes
where it stopped and produces what an uninterrupted run would.

Not run against a live CARLA server on the machines this project is built on (none can run
there); the loop, sampling, naming, encoding, resume and error handling are tested against a fake
client at the API boundary (tests/tools/test_carla_collect.py). Every CarlaConfig setting is a flag
(--height_m '[20, 80]'), and settings can come from a YAML file (--config FILE; --print_config writes one).
"""

from __future__ import annotations

import math
import queue
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from dapm_lightning.data.files import write_image
from dapm_lightning.data.uapd import format_uapd_filename
from dapm_lightning.geometry.constants import MAX_DEPTH_M, POSE_RANGES
from dapm_lightning.geometry.depth_codec import depth_to_grey

CARLA_DEPTH_FAR_M = 1000.0
"""CARLA's depth camera encodes planar depth up to 1000 m in its R, G, B channels."""


@dataclass
class CarlaConfig:
    """Acquisition settings; defaults are the paper's (parameter table of "Data Acquisition").

    Args:
        out: output root; images go to OUT/{train,val}/{rgb,depth}/NAME.png in UAPD naming.
        host: the CARLA server's host name.
        port: the CARLA server's port.
        timeout_s: seconds to wait for the server and for each sensor frame.
        towns: maps, in turn, each for reset_every samples (the paper leaves Town02 out).
        samples: number of samples (indices 0 .. samples-1; ones already on disk are skipped).
        reset_every: reload the town and respawn the traffic every this many samples.
        seed: every sample's draw depends only on (seed, index).
        val_fraction: share of samples written to the val split.
        image_size: width and height of the square images in pixels.
        vehicles: vehicles spawned on autopilot after each reset.
        walkers: walkers spawned with AI controllers after each reset.
        hour: range of the hour of the day (sun altitude), drawn uniformly.
        x_m: range of the camera's x position in metres.
        y_m: range of the camera's y position in metres.
        height_m: range of the camera height above the ground in metres (UAPD's, geometry.POSE_RANGES).
        pitch_deg: range of the pitch in degrees (UAPD's).
        roll_deg: range of the roll in degrees (UAPD's).
        yaw_deg: range of the yaw in degrees.
        fov_deg: range of the horizontal field of view in degrees (UAPD's).
        lens_k: range of CARLA's lens_k distortion parameter.
        lens_kcube: range of CARLA's lens_kcube distortion parameter.
        lens_x_size: range of CARLA's lens_x_size.
        lens_y_size: range of CARLA's lens_y_size.
        pause_s: pause after each sample in seconds (the paper's 200 ms).
    """

    out: str = "data/uapd_carla"
    host: str = "localhost"
    port: int = 2000
    timeout_s: float = 20.0
    towns: tuple[str, ...] = ("Town01", "Town03", "Town04", "Town05", "Town06", "Town07", "Town10HD")
    samples: int = 50000
    reset_every: int = 500
    seed: int = 0
    val_fraction: float = 0.02
    image_size: int = 512
    vehicles: int = 200
    walkers: int = 200
    hour: tuple[float, float] = (8.0, 17.0)
    x_m: tuple[float, float] = (-50.0, 50.0)
    y_m: tuple[float, float] = (-50.0, 50.0)
    height_m: tuple[float, float] = POSE_RANGES["height"]
    pitch_deg: tuple[float, float] = POSE_RANGES["pitch"]
    roll_deg: tuple[float, float] = POSE_RANGES["roll"]
    yaw_deg: tuple[float, float] = (-180.0, 180.0)
    fov_deg: tuple[float, float] = POSE_RANGES["fov"]
    lens_k: tuple[float, float] = (-0.5, 0.5)
    lens_kcube: tuple[float, float] = (-0.2, 0.2)
    lens_x_size: tuple[float, float] = (0.3, 0.7)
    lens_y_size: tuple[float, float] = (0.3, 0.7)
    pause_s: float = 0.2

    def __post_init__(self) -> None:
        self.towns = tuple(self.towns)
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type == "tuple[float, float]":
                if len(value) != 2 or float(value[0]) > float(value[1]):
                    raise ValueError(f"{f.name} must be a range [low, high] with low <= high, got {list(value)}")
                setattr(self, f.name, (float(value[0]), float(value[1])))
        if not self.towns:
            raise ValueError("towns must name at least one map")
        for name, least in (("samples", 0), ("reset_every", 1), ("image_size", 1)):
            if getattr(self, name) < least:
                raise ValueError(f"--{name} must be at least {least}, got {getattr(self, name)}")
        if not 0.0 <= self.val_fraction <= 1.0:
            raise ValueError(f"val_fraction must lie in [0, 1], got {self.val_fraction}")


@dataclass(frozen=True)
class SampleParams:
    """One sample's draw."""

    index: int
    town: str
    split: str
    hour: float
    x: float
    y: float
    height: float
    pitch: float
    roll: float
    yaw: float
    fov: float
    lens: dict[str, float]

    def name(self) -> str:
        """UAPD file name (values rounded to 2 decimals: the camera is placed with the rounded values)."""
        return format_uapd_filename([self.town, f"{self.index:06d}"], (self.height, self.pitch, self.roll, self.fov),
                                    x=self.x, y=self.y, yaw=self.yaw)


def sample_params(config: CarlaConfig, index: int) -> SampleParams:
    """The draw of sample ``index``: a function of (seed, index) only, so runs resume deterministically."""
    rng = np.random.default_rng([config.seed, index])

    def draw(bounds: tuple[float, float]) -> float:
        return round(float(rng.uniform(*bounds)), 2)

    town = config.towns[(index // config.reset_every) % len(config.towns)]
    split = "val" if rng.random() < config.val_fraction else "train"
    return SampleParams(index, town, split, draw(config.hour), draw(config.x_m), draw(config.y_m),
                        draw(config.height_m), draw(config.pitch_deg), draw(config.roll_deg), draw(config.yaw_deg),
                        draw(config.fov_deg),
                        {"lens_k": draw(config.lens_k), "lens_kcube": draw(config.lens_kcube),
                         "lens_x_size": draw(config.lens_x_size), "lens_y_size": draw(config.lens_y_size)})


def sun_altitude_deg(hour: float) -> float:
    """A simple solar elevation for the hour (0 at 6:00 and 18:00, 70 at noon)."""
    return 70.0 * math.sin(math.pi * (hour - 6.0) / 12.0)


def decode_carla_depth(bgra: np.ndarray) -> np.ndarray:
    """CARLA depth image ``[H, W, 4]`` uint8 BGRA -> planar depth in metres (float64)."""
    b, g, r = (bgra[..., k].astype(np.float64) for k in range(3))
    return CARLA_DEPTH_FAR_M * (r + g * 256.0 + b * 65536.0) / (256.0 ** 3 - 1.0)


def done_indices(out: Path) -> set[int]:
    """Indices whose rgb and depth files are both on disk (resume skips them)."""
    pattern = re.compile(r"^[^_]+_(\d{6})_")
    done: set[int] = set()
    for split in ("train", "val"):
        rgb_dir, depth_dir = out / split / "rgb", out / split / "depth"
        if not rgb_dir.is_dir():
            continue
        for path in rgb_dir.glob("*.png"):
            match = pattern.match(path.name)
            if match and path.is_file() and (depth_dir / path.name).is_file():
                done.add(int(match.group(1)))
    return done


def _import_carla() -> Any:
    try:
        import carla
    except ImportError as error:
        raise RuntimeError("the CARLA client package is not installed: pip install 'dapm-lightning[carla]' "
                           "(its version must match the server's)") from error
    return carla


class CarlaCollector:
    """The acquisition loop. ``carla`` is the client module (the real one by default, a fake in tests)."""

    def __init__(self, config: CarlaConfig, carla: Any | None = None) -> None:
        self.config, self.carla = config, carla if carla is not None else _import_carla()
        self.out = Path(config.out)
        self.client: Any = None
        self.world: Any = None
        self.actors: list[Any] = []
        self.town: str | None = None

    def connect(self) -> None:
        """Connect, or fail with a message saying what to start."""
        cfg = self.config
        try:
            self.client = self.carla.Client(cfg.host, cfg.port)
            self.client.set_timeout(cfg.timeout_s)
            self.client.get_server_version()
        except RuntimeError as error:
            raise RuntimeError(f"no CARLA server answered at {cfg.host}:{cfg.port} within {cfg.timeout_s:.0f} s "
                               f"(start CarlaUE4.sh / CarlaUE4.exe first): {error}") from error

    def reset(self, town: str) -> None:
        """Load ``town`` in synchronous mode and spawn the traffic (vehicles on autopilot, walkers with AI)."""
        self._destroy_actors()
        self.world = self.client.load_world(town)
        settings = self.world.get_settings()
        settings.synchronous_mode = True
        settings.fixed_delta_seconds = 0.05
        self.world.apply_settings(settings)
        library = self.world.get_blueprint_library()
        spawn_points = list(self.world.get_map().get_spawn_points())
        vehicles = library.filter("vehicle.*")
        for k, point in enumerate(spawn_points[: self.config.vehicles]):
            actor = self.world.try_spawn_actor(vehicles[k % len(vehicles)], point)
            if actor is not None:
                actor.set_autopilot(True)
                self.actors.append(actor)
        walkers = library.filter("walker.pedestrian.*")
        controller_bp = library.find("controller.ai.walker")
        for k in range(self.config.walkers):
            location = self.world.get_random_location_from_navigation()
            if location is None:
                continue
            walker = self.world.try_spawn_actor(walkers[k % len(walkers)], self.carla.Transform(location))
            if walker is None:
                continue
            controller = self.world.spawn_actor(controller_bp, self.carla.Transform(), attach_to=walker)
            self.world.tick()
            controller.start()
            controller.go_to_location(self.world.get_random_location_from_navigation())
            self.actors += [walker, controller]
        self.town = town

    def _destroy_actors(self) -> None:
        for actor in reversed(self.actors):
            actor.destroy()
        self.actors = []

    def capture(self, params: SampleParams) -> tuple[np.ndarray, np.ndarray]:
        """Place an RGB and a depth camera with the sample's pose and lens; return ``(bgr, depth grey)``."""
        cfg, carla = self.config, self.carla
        weather = carla.WeatherParameters.ClearNoon
        weather.sun_altitude_angle = sun_altitude_deg(params.hour)
        self.world.set_weather(weather)
        transform = carla.Transform(carla.Location(x=params.x, y=params.y, z=params.height),
                                    carla.Rotation(pitch=params.pitch, yaw=params.yaw, roll=params.roll))
        library = self.world.get_blueprint_library()
        sensors, queues = [], []
        for kind in ("sensor.camera.rgb", "sensor.camera.depth"):
            blueprint = library.find(kind)
            blueprint.set_attribute("image_size_x", str(cfg.image_size))
            blueprint.set_attribute("image_size_y", str(cfg.image_size))
            blueprint.set_attribute("fov", str(params.fov))
            for key, value in params.lens.items():
                blueprint.set_attribute(key, str(value))
            sensor = self.world.spawn_actor(blueprint, transform)
            frames: queue.Queue[Any] = queue.Queue()
            sensor.listen(frames.put)
            sensors.append(sensor)
            queues.append(frames)
        try:
            self.world.tick()
            images = [q.get(timeout=cfg.timeout_s) for q in queues]
        finally:
            for sensor in sensors:
                sensor.stop()
                sensor.destroy()
        rgb, depth = (np.frombuffer(bytes(im.raw_data), np.uint8).reshape(im.height, im.width, 4) for im in images)
        depth_m = decode_carla_depth(depth)
        return np.ascontiguousarray(rgb[..., :3]), depth_to_grey(np.minimum(depth_m, MAX_DEPTH_M))

    def run(self) -> int:
        """Collect every sample not yet on disk; returns how many were written in this run."""
        cfg = self.config
        done = done_indices(self.out)
        todo = [i for i in range(cfg.samples) if i not in done]
        if not todo:
            return 0
        self.connect()
        written = 0
        try:
            for index in todo:
                params = sample_params(cfg, index)
                if params.town != self.town or index % cfg.reset_every == 0:
                    self.reset(params.town)
                bgr, grey = self.capture(params)
                for sub in ("rgb", "depth"):
                    (self.out / params.split / sub).mkdir(parents=True, exist_ok=True)
                name = params.name()
                depth_path = self.out / params.split / "depth" / name
                # each written whole or not at all (a kill mid-write left a cut PNG that resume took for done)
                write_image(depth_path, grey)
                write_image(self.out / params.split / "rgb" / name, bgr)  # rgb last: it marks the sample done
                written += 1
                time.sleep(cfg.pause_s)
        finally:
            self._destroy_actors()
        return written


def build_parser() -> Any:
    """The collect-carla parser: every :class:`CarlaConfig` field as a flag, ``--config``, ``--print_config``."""
    from jsonargparse import ActionConfigFile, ArgumentParser

    parser = ArgumentParser(prog="dapm-lightning collect-carla", description=__doc__)
    parser.add_argument("--config", action=ActionConfigFile, help="settings from a YAML file")
    parser.add_class_arguments(CarlaConfig, nested_key=None, as_group=False)
    return parser


def parse_config(argv: Sequence[str]) -> CarlaConfig:
    """The :class:`CarlaConfig` of a command line; a value it refuses is a usage error (exit status 2)."""
    parser = build_parser()
    namespace = parser.parse_args(list(argv))
    try:
        return CarlaConfig(**{f.name: namespace[f.name] for f in fields(CarlaConfig)})
    except ValueError as error:
        parser.error(str(error))


def collect_main(argv: Sequence[str]) -> None:
    """``dapm-lightning collect-carla --out DIR [--samples N] [--host H --port P] [--seed S] ...``."""
    config = parse_config(argv)
    written = CarlaCollector(config).run()
    print(f"wrote {written} sample(s) to {config.out} (depth: CARLA planar depth, 8-bit log encoded; "
          f"train with depth_kind: planar)")

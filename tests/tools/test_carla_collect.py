"""The CARLA collector against a fake client at the API boundary (no CARLA server can run here)."""

import sys
from dataclasses import dataclass, field
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from dapm_lightning.data import UAPDDataset, parse_uapd_filename
from dapm_lightning.geometry import depth_to_grey
from dapm_lightning.tools.carla_collect import (
    CarlaCollector,
    CarlaConfig,
    _import_carla,
    decode_carla_depth,
    done_indices,
    sample_params,
)

FAKE_DEPTH_M = 50.0


def carla_depth_bgra(depth_m, shape):
    value = np.uint32(round(depth_m / 1000.0 * (256 ** 3 - 1)))
    bgra = np.zeros((*shape, 4), np.uint8)
    bgra[..., 2] = value & 255
    bgra[..., 1] = (value >> 8) & 255
    bgra[..., 0] = (value >> 16) & 255
    bgra[..., 3] = 255
    return bgra


@dataclass
class Blueprint:
    id: str
    attributes: dict = field(default_factory=dict)

    def set_attribute(self, key, value):
        self.attributes[key] = value


class Library:
    def filter(self, pattern):
        return [Blueprint(pattern.replace("*", str(k))) for k in range(3)]

    def find(self, name):
        return Blueprint(name)


class Actor:
    def __init__(self, world, blueprint, transform):
        self.world, self.blueprint, self.transform = world, blueprint, transform
        self.callback, self.alive = None, True
        world.alive.append(self)

    def set_autopilot(self, on):
        self.autopilot = on

    def start(self):
        pass

    def go_to_location(self, location):
        pass

    def listen(self, callback):
        self.callback = callback

    def stop(self):
        self.callback = None

    def destroy(self):
        self.alive = False
        self.world.alive.remove(self)


class World:
    def __init__(self, client, town):
        self.client, self.town, self.alive, self.captured = client, town, [], []

    def get_settings(self):
        return SimpleNamespace(synchronous_mode=False, fixed_delta_seconds=None)

    def apply_settings(self, settings):
        self.settings = settings

    def get_blueprint_library(self):
        return Library()

    def get_map(self):
        return SimpleNamespace(get_spawn_points=lambda: [SimpleNamespace(k=k) for k in range(5)])

    def try_spawn_actor(self, blueprint, transform):
        return Actor(self, blueprint, transform)

    def spawn_actor(self, blueprint, transform, attach_to=None):
        return Actor(self, blueprint, transform)

    def get_random_location_from_navigation(self):
        return SimpleNamespace(x=0.0, y=0.0, z=0.0)

    def set_weather(self, weather):
        self.weather = weather

    def tick(self):
        sensors = [a for a in self.alive if a.callback is not None]
        if sensors and self.client.fail_on_capture == len(self.client.captures):
            raise KeyboardInterrupt("simulated interruption")
        for sensor in sensors:
            size = int(sensor.blueprint.attributes["image_size_y"]), int(sensor.blueprint.attributes["image_size_x"])
            if sensor.blueprint.id.endswith("depth"):
                data = carla_depth_bgra(FAKE_DEPTH_M, size)
            else:
                data = np.full((*size, 4), len(self.client.captures) % 255, np.uint8)
            sensor.callback(SimpleNamespace(raw_data=data.tobytes(), height=size[0], width=size[1]))
        if sensors:
            self.client.captures.append({s.blueprint.id: dict(s.blueprint.attributes, transform=s.transform)
                                         for s in sensors})


class FakeCarla:
    """The slice of the ``carla`` module the collector uses."""

    def __init__(self, server_up=True, fail_on_capture=None):
        self.server_up, self.fail_on_capture = server_up, fail_on_capture
        self.captures, self.worlds = [], []
        fake = self

        class Client:
            def __init__(self, host, port):
                self.address = (host, port)

            def set_timeout(self, seconds):
                pass

            def get_server_version(self):
                if not fake.server_up:
                    raise RuntimeError("time-out of 20000ms while waiting for the simulator")
                return "0.9.15"

            def load_world(self, town):
                fake.worlds.append(World(fake, town))
                return fake.worlds[-1]

        self.Client = Client
        self.Transform = lambda location=None, rotation=None: SimpleNamespace(location=location, rotation=rotation)
        self.Location = lambda x=0.0, y=0.0, z=0.0: SimpleNamespace(x=x, y=y, z=z)
        self.Rotation = lambda pitch=0.0, yaw=0.0, roll=0.0: SimpleNamespace(pitch=pitch, yaw=yaw, roll=roll)
        self.WeatherParameters = SimpleNamespace(ClearNoon=SimpleNamespace(sun_altitude_angle=45.0))


def config(tmp_path, **kwargs):
    return CarlaConfig(out=str(tmp_path), samples=6, reset_every=3, towns=("Town01", "Town03"), image_size=16,
                       vehicles=4, walkers=2, pause_s=0.0, val_fraction=0.3, **kwargs)


def test_sampling_is_per_index_and_within_the_paper_ranges():
    cfg = CarlaConfig()
    a, b = sample_params(cfg, 7), sample_params(cfg, 7)
    assert a == b and sample_params(cfg, 8) != a
    draws = [sample_params(cfg, i) for i in range(300)]
    assert "Town02" not in cfg.towns
    for p in draws:
        assert 10 <= p.height <= 100 and -100 <= p.pitch <= 10 and -30 <= p.roll <= 30 and 30 <= p.fov <= 120
        assert -50 <= p.x <= 50 and 8 <= p.hour <= 17 and -0.2 <= p.lens["lens_kcube"] <= 0.2
        parsed = parse_uapd_filename(p.name())
        assert (parsed["height"], parsed["pitch"], parsed["roll"], parsed["fov"]) == (p.height, p.pitch, p.roll, p.fov)


def test_loop_writes_uapd_files_with_encoded_depth(tmp_path):
    fake = FakeCarla()
    assert CarlaCollector(config(tmp_path), fake).run() == 6
    assert [w.town for w in fake.worlds] == ["Town01", "Town03"]
    assert all(not w.alive for w in fake.worlds)  # every actor destroyed
    names = sorted(p.name for split in ("train", "val") for p in (tmp_path / split / "rgb").glob("*.png"))
    assert len(names) == 6 and done_indices(tmp_path) == set(range(6))
    for split in ("train", "val"):
        if (tmp_path / split).is_dir():
            ds = UAPDDataset(tmp_path, split)
            for i in range(len(ds)):
                grey = cv2.imread(str(tmp_path / split / "depth" / ds.names[i]), cv2.IMREAD_UNCHANGED)
                assert (grey == depth_to_grey(np.array(FAKE_DEPTH_M))).all()
    first = fake.captures[0]["sensor.camera.rgb"]
    p0 = sample_params(config(tmp_path), 0)
    assert float(first["fov"]) == p0.fov and float(first["lens_k"]) == p0.lens["lens_k"]
    assert first["transform"].rotation.roll == p0.roll and first["transform"].location.z == p0.height


def test_resume_after_interruption_gives_the_uninterrupted_result(tmp_path):
    with pytest.raises(KeyboardInterrupt):
        CarlaCollector(config(tmp_path / "a"), FakeCarla(fail_on_capture=4)).run()
    assert done_indices(tmp_path / "a") == {0, 1, 2, 3}
    resumed = FakeCarla()
    assert CarlaCollector(config(tmp_path / "a"), resumed).run() == 2
    assert [w.town for w in resumed.worlds] == ["Town03"]
    CarlaCollector(config(tmp_path / "b"), FakeCarla()).run()
    names = lambda root: sorted(p.name for p in root.rglob("*.png"))  # noqa: E731
    assert names(tmp_path / "a") == names(tmp_path / "b")
    assert CarlaCollector(config(tmp_path / "b"), FakeCarla(server_up=False)).run() == 0  # nothing left to do


def test_missing_server_and_missing_package_are_clear(tmp_path, monkeypatch):
    with pytest.raises(RuntimeError, match="no CARLA server answered at localhost:2000"):
        CarlaCollector(config(tmp_path), FakeCarla(server_up=False)).run()
    monkeypatch.setitem(sys.modules, "carla", None)
    with pytest.raises(RuntimeError, match="pip install"):
        _import_carla()


def test_carla_depth_decoding():
    for depth in (0.0, 1.5, 50.0, 999.0):
        assert decode_carla_depth(carla_depth_bgra(depth, (1, 1)))[0, 0] == pytest.approx(depth, abs=1e-4)


def test_a_sample_that_cannot_be_written_stops_the_run_and_is_never_taken_for_done(tmp_path):
    """Each file is written whole or not at all, and a failed write stops the run naming the file (before:
    ``cv2.imwrite``'s False was ignored, the run reported the sample written, and a kill mid-write left a cut rgb
    PNG that every resume took for a finished sample)."""
    from dapm_lightning.data.files import WriteError

    cfg = config(tmp_path)
    params = sample_params(cfg, 2)
    blocked = tmp_path / params.split / "rgb" / params.name()
    blocked.mkdir(parents=True)  # a folder where the rgb file goes: its write fails
    with pytest.raises(WriteError, match=params.name()):
        CarlaCollector(cfg, FakeCarla()).run()
    assert done_indices(tmp_path) == {0, 1} and not list(tmp_path.rglob("*.tmp"))
    blocked.rmdir()
    assert CarlaCollector(cfg, FakeCarla()).run() == 4 and done_indices(tmp_path) == set(range(6))


def test_a_value_the_settings_refuse_is_a_usage_error_naming_the_option(tmp_path, capsys):
    """It was exit status 1 with one message for three settings ("samples must be >= 0, reset_every and ...")."""
    from dapm_lightning.tools.carla_collect import parse_config

    for option, value, least in (("--samples", "-1", 0), ("--reset_every", "0", 1), ("--image_size", "0", 1)):
        with pytest.raises(SystemExit) as info:
            parse_config(["--out", str(tmp_path), option, value])
        assert info.value.code == 2
        assert f"error: {option} must be at least {least}, got {value}" in capsys.readouterr().err

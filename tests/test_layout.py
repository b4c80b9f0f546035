"""The package's layout contracts that a user or an outside check relies on (docs/design.md §8)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import keo_service
from keo_service.core.chain import Chain
from keo_service.core.kinematics import flange_pose, load_robot
from tests.conftest import CONFIGS, REPO

CORE_MODULES = [
    "keo_service.core",
    "keo_service.core.chain",
    "keo_service.core.model_corrections",
    "keo_service.core.errors",
    "keo_service.core.estimator",
    "keo_service.core.kinematics",
    "keo_service.core.observer",
    "keo_service.core.rotations",
    "keo_service.core.settings",
    "keo_service.core.timing",
]
FORBIDDEN_IN_CORE = ["asyncio", "zenoh", "msgspec", "rerun", "matplotlib"]


def test_importing_the_core_loads_no_network_messages_plots_or_asyncio():
    code = (
        "import sys\n"
        + "".join(f"import {m}\n" for m in CORE_MODULES)
        + f"print(','.join(m for m in {FORBIDDEN_IN_CORE!r} if m in sys.modules))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.strip()
    assert out == "", f"importing keo_service.core loaded {out}"


def test_importing_the_package_stays_light_until_a_public_name_is_used():
    code = (
        "import sys, keo_service\n"
        "before = 'zenoh' in sys.modules\n"
        "keo_service.Client\n"
        "print(before, 'zenoh' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.split()
    assert out == ["False", "True"]


def test_reading_a_config_loads_no_kinematics_library():
    # keo estimate starts parsing the tracker file while Pinocchio loads: the config must be
    # readable before that
    code = (
        "import sys\n"
        "import keo_service\n"
        "from keo_service.cli import common\n"
        f"common.load({str(CONFIGS / 'demo.toml')!r})\n"
        "keo_service.EstimatorSettings()\n"  # the public name, too
        "print('pinocchio' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.split()
    assert out == ["False"]


def test_public_surface_resolves_every_name():
    assert "Client" in keo_service.__all__
    for name in keo_service.__all__:
        assert getattr(keo_service, name) is not None, name
    with pytest.raises(AttributeError):
        _ = keo_service.NoSuchName


@pytest.mark.parametrize("urdf", ["mh180.urdf", "ur10.urdf"])
def test_vectorised_chain_equals_pinocchio_at_random_poses(urdf):
    robot = load_robot(CONFIGS / "robots" / urdf, "base_link", "tool0")
    rng = np.random.default_rng(7)
    lower = np.maximum(robot.lower, -2 * np.pi)
    upper = np.minimum(robot.upper, 2 * np.pi)
    q = rng.uniform(lower, upper, size=(1000, robot.nq))
    batch = Chain(robot).flange_poses(q)
    data = robot.create_data()
    reference = np.array([flange_pose(robot, data, qi).homogeneous for qi in q])
    assert np.max(np.abs(batch - reference)) < 1e-12


def test_every_exception_class_derives_from_keo_error():
    """One root for keo's own errors: a caller can catch them all with `KeoError`."""
    import importlib
    import inspect
    import pkgutil

    from keo_service import adapters
    from keo_service.core.errors import KeoError

    found = []
    for package in (keo_service, adapters):
        for info in pkgutil.walk_packages(package.__path__, f"{package.__name__}."):
            if info.name.endswith("__main__"):
                continue
            module = importlib.import_module(info.name)
            for _name, cls in inspect.getmembers(module, inspect.isclass):
                if issubclass(cls, BaseException) and cls.__module__ == module.__name__:
                    found.append(cls)
    assert len(found) >= 10  # the ten of this writing, and any added since
    assert [c.__qualname__ for c in found if not issubclass(c, KeoError)] == []


def test_docstrings_cite_the_design_page_in_the_repository():
    """The contracts live in docs/design.md: every section cited exists there, and nothing
    cites a file outside the repository."""
    import re

    root = CONFIGS.parent
    sections = set(re.findall(r"^## (\d)\. ", (root / "docs" / "design.md").read_text(), re.M))
    cited = set()
    for folder in ("keo_service", "tests", "examples"):
        for path in (root / folder).rglob("*.py"):
            text = path.read_text()
            assert "DESIGN" + ".md" not in text, path
            cited |= set(re.findall(r"docs/design\.md §(\d)", text))
    assert cited
    assert cited <= sections, cited - sections


def test_the_wheel_installs_keo_service_only(tmp_path):
    """The adapters install as keo_service.adapters: a top-level `adapters` package would
    clash with PyPI's package of that name."""
    import zipfile

    import hatchling.builders.wheel as wheel_builder

    built = wheel_builder.WheelBuilder(str(REPO)).build(
        directory=str(tmp_path), versions=["standard"]
    )
    names = zipfile.ZipFile(next(iter(built))).namelist()
    assert {n.split("/")[0] for n in names} == {"keo_service", "keo-0.1.0.dist-info"}
    assert "keo_service/adapters/devices.py" in names
    assert "keo_service/adapters/egm/egm_pb2.py" in names

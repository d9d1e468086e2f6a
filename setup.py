"""The installed layout (README "Python API"): ``estimators``, ``protocols`` and ``service`` under ``ins_health``.

The repository keeps its three top-level folders, and an editable install (``make``: the tests,
benchmarks and ``python -m protocols.zenoh_router`` of a checkout) maps them as they are. A wheel
puts them under the one package ``ins_health``, so that installing the project adds one top-level
name and not three generic ones that a user's own ``service`` package would collide with: the
folders are moved there as they are built, and their absolute imports of each other (``from
service.cli import …``) rewritten to the new names (``from ins_health.service.cli import …``).
Module names the code spawns or reads at run time are derived from ``__spec__``/``__package__``,
not written out, so they hold in both layouts.
"""

import re
import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

TOP = "ins_health"
INNER = ("estimators", "protocols", "service")
IMPORT = re.compile(rf"^(\s*)(from|import)(\s+)({'|'.join(INNER)})(?=[.\s])", re.MULTILINE)


def under_top(source: str) -> str:
    """``source`` with its imports of the three folders made imports of them under :data:`TOP`."""
    return IMPORT.sub(rf"\1\2\3{TOP}.\4", source)


class BuildUnderTop(build_py):
    """``build_py`` that moves the three folders under :data:`TOP` in a wheel (module docstring)."""

    def run(self) -> None:
        super().run()
        if getattr(self, "editable_mode", False):
            return
        root = Path(self.build_lib)
        for name in INNER:
            if (root / name).is_dir():
                shutil.rmtree(root / TOP / name, ignore_errors=True)
                shutil.move(str(root / name), str(root / TOP / name))
        for path in (root / TOP).rglob("*.py"):
            text = path.read_text(encoding="utf-8")
            if (moved := under_top(text)) != text:
                path.write_text(moved, encoding="utf-8")


try:
    from setuptools.command.bdist_wheel import bdist_wheel
except ImportError:  # setuptools before 70.1
    from wheel.bdist_wheel import bdist_wheel


class WheelUnderTop(bdist_wheel):
    """``bdist_wheel`` whose ``top_level.txt`` names the one package the wheel holds."""

    def egg2dist(self, egginfo_path: str, distinfo_path: str) -> None:
        super().egg2dist(egginfo_path, distinfo_path)
        top_level = Path(distinfo_path) / "top_level.txt"
        if top_level.exists():
            top_level.write_text(TOP + "\n", encoding="utf-8")


setup(cmdclass={"build_py": BuildUnderTop, "bdist_wheel": WheelUnderTop})

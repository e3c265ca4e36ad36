"""Build hook: ship the repository's top-level ``data/`` folder inside the wheel as ``pgm_wm/data``.

The bundled datasets live in ``data/`` at the top of the repository (next to the book and the
tests); the package reads them with ``importlib.resources`` from ``pgm_wm/data`` once installed
(:func:`pgm_wm.datasets.data_dir`). All metadata is in ``pyproject.toml``; this file only adds
the copy step to ``build_py``. An editable install needs no copy: there the loader reads the
clone's ``data/`` folder directly.
"""

from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent
# everything the loader and its integrity check read, plus the provenance notes and licences
DATA_PATTERNS = ("*.npz", "*.csv", "SHA256SUMS", "*.txt", "README.md")


def data_files() -> list[Path]:
    files = sorted({f for pattern in DATA_PATTERNS for f in (ROOT / "data").glob(pattern) if f.is_file()})
    if not any(f.name == "SHA256SUMS" for f in files):
        raise RuntimeError(f"{ROOT / 'data'}: SHA256SUMS not found; the wheel would ship no usable data")
    return files


class BuildPyWithData(build_py):
    """``build_py`` plus a copy of ``data/`` into ``<build_lib>/pgm_wm/data``."""

    def run(self) -> None:
        super().run()
        if getattr(self, "editable_mode", False):
            return
        target = Path(self.build_lib) / "pgm_wm" / "data"
        self.mkpath(str(target))
        for src in data_files():
            self.copy_file(str(src), str(target / src.name), preserve_mode=False)

    def get_outputs(self, include_bytecode: bool = True) -> list[str]:
        outputs = super().get_outputs(include_bytecode)
        if getattr(self, "editable_mode", False):
            return outputs
        target = Path(self.build_lib) / "pgm_wm" / "data"
        return outputs + [str(target / src.name) for src in data_files()]


setup(cmdclass={"build_py": BuildPyWithData})

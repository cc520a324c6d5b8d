"""Build hook: a wheel carries the shipped configs and model manifest inside the package.

Everything else is in pyproject.toml. In a source checkout the package reads the top-level
`configs/` and `models/` directly (meridian_torch/core/paths.py); a built wheel has no checkout
around it, so build_py copies those files to `meridian_torch/_bundled/`.
"""

from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

SHIPPED = {"configs": ["*.yaml"], "models": ["manifest.yaml", "README.md"]}


class BuildPyWithShippedFiles(build_py):
    def run(self) -> None:
        super().run()
        root = Path(__file__).resolve().parent
        for folder, patterns in SHIPPED.items():
            target = Path(self.build_lib) / "meridian_torch" / "_bundled" / folder
            target.mkdir(parents=True, exist_ok=True)
            for pattern in patterns:
                for src in sorted((root / folder).glob(pattern)):
                    self.copy_file(str(src), str(target / src.name))


setup(cmdclass={"build_py": BuildPyWithShippedFiles})

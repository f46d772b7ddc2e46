"""Files that ship inside the package, found with :mod:`importlib.resources` so that an
installed wheel finds them as an editable checkout does:

    scenes/          built-in scenes (Mitsuba 3 XML) and their meshes
    models/          network presets (``<name>.json``) and the shipped model ``default.pt``
                     with its card ``default.md``
    configs/data/    data-set budgets for ``ppmrecon-train generate``
    configs/train/   training settings for ``ppmrecon-train fit``

They are the only copies in the repository. Mitsuba reads scene files and meshes by
path, so the package must be installed as files (any ``pip install``), not imported
from a zip archive.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

from ..errors import PpmreconError


def data_path(*parts: str) -> Path:
    """The real path of ``ppmrecon/data/<parts>`` (it need not exist).

    >>> data_path("scenes", "plane_point.xml").is_file()
    True
    """
    root = files(__name__)
    if not isinstance(root, Path):  # a zip import: Mitsuba could not open the files
        raise PpmreconError(f"ppmrecon's data files are inside an archive ({root}); install ppmrecon "
                            "with pip so that they are plain files")
    return root.joinpath(*parts)


SCENES = data_path("scenes")
MODELS = data_path("models")
CONFIGS = data_path("configs")

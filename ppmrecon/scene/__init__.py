"""Scene loading: built-in scenes, Mitsuba 3 XML, and the Mitsuba 0.6 import.

One module per plugin kind for the 0.6 import (:mod:`.spectra`, :mod:`.textures`,
:mod:`.bsdfs`, :mod:`.emitters`, :mod:`.shapes`, :mod:`.sensors`), the 0.6 file
structure in :mod:`.xml06`, the ordered rule table in :mod:`.mi06`, shared machinery in
:mod:`.common` and the loader in :mod:`.loader`. Imports only go downwards
(loader -> mi06 -> plugin modules -> common), so there is no cycle.
"""

from .common import SceneError, ensure_variant
from .loader import DEFAULT_SCENE, SCENES_DIR, LoadedScene, builtin_scenes, load_scene, load_tree

__all__ = ["SceneError", "ensure_variant", "DEFAULT_SCENE", "SCENES_DIR", "LoadedScene", "builtin_scenes",
           "load_scene", "load_tree"]

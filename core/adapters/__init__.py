"""Importers that convert existing capture layouts into scene bundles (:mod:`core.bundle`).

* :func:`import_drivestudio` - drivestudio / OmniRe processed Waymo scenes.
* :func:`import_nerfstudio` - nerfstudio captures (``transforms.json`` + images).
"""

from core.adapters.drivestudio import WAYMO_CAMERA_NAMES, import_drivestudio
from core.adapters.nerfstudio import import_nerfstudio

__all__ = ["WAYMO_CAMERA_NAMES", "import_drivestudio", "import_nerfstudio"]

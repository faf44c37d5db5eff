"""The registration file REG.json (a public format).

```json
{"model": "translation" | "rigid" | "similarity" | "affine" | "homography",
 "matrix": [[h11, h12, h13], [h21, h22, h23], [h31, h32, h33]],
 "mi": 1.52, "nmi": 1.27, "bins": 32, "log_base": 2.0}
```

``matrix`` maps infrared pixel coordinates to visible pixel coordinates
(homogeneous, pixel centres at integers as OpenCV): ``[x_v, y_v, w] = matrix
@ [x_ir, y_ir, 1]``, then divide by ``w``. ``mi`` is the mutual information in
units of ``log_base`` (2: bits) from a joint histogram of ``bins`` x ``bins``
cells, ``nmi`` the normalised mutual information (H(A) + H(B)) / H(A, B),
both over the overlap at infrared resolution. See docs/registration.md.

Writing needs only ``json`` (pydantic's import would be a seventh of a whole ``thermofield register``);
reading validates with :class:`services.formats.registration_schema.RegistrationFile`, imported on first read.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from services.formats.files import write_text_atomically
from services.registration.register import Registration

if TYPE_CHECKING:
    from services.formats.registration_schema import RegistrationFile


def registration_json(registration: Registration) -> str:
    """The REG.json text of a registration result."""
    document = {"model": registration.model, "matrix": np.asarray(registration.matrix, dtype=float).tolist(),
                "mi": float(registration.mi), "nmi": float(registration.nmi), "bins": int(registration.bins),
                "log_base": float(registration.log_base)}
    return json.dumps(document, indent=2) + "\n"


def parse_registration(text: str, source: str = "registration") -> RegistrationFile:
    """Validate REG.json text; errors name ``source`` and the field."""
    from services.formats.json_files import validate_json
    from services.formats.registration_schema import RegistrationFile

    return validate_json(RegistrationFile, text, source)


def load_registration(path: str | Path) -> RegistrationFile:
    """Read and validate a REG.json file."""
    from services.formats.json_files import read_text

    return parse_registration(read_text(path, "registration file"), str(path))


def save_registration(registration: Registration, path: str | Path) -> None:
    """Write REG.json atomically (a reader never sees half a file)."""
    write_text_atomically(path, registration_json(registration))

"""Made the plates of docs/figures/realism_sheet_images.jpg (realism.md "Contact sheets"; issue 18, 6e5bd61).

Three backplate photographs for the realism contact sheet (docs/realism.md): perspective views
of shared HDRIs, 480 x 320, written as JPEG to OUT (default out/plates).

    python experiments/figures/realism_plates.py [OUT]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from PIL import Image

from blsm.camera import look_at_camera
from blsm.color import linear_to_srgb
from synth.backgrounds import hdri as bg
from synth.ground import env_backdrop

out = Path(sys.argv[1] if len(sys.argv) > 1 else "out/plates")
out.mkdir(parents=True, exist_ok=True)
for i, name in enumerate(["city.exr", "courtyard.exr", "sunrise.exr"]):
    env = bg.load_hdri(Path("../shared/assets/hdri") / name, 1024)
    eye, at = np.array([0.0, 1.7, 0.0]), np.array([np.sin(i * 2.0), 1.5, np.cos(i * 2.0)])
    img = env_backdrop(look_at_camera(eye, at, width=480, height=320), env, 0.0, 1.0)
    rgb = np.clip(linear_to_srgb(np.clip(img, 0.0, None)), 0.0, 1.0)
    Image.fromarray((rgb * 255).astype(np.uint8)).save(out / f"plate_{i}.jpg", quality=92)
print(f"{out}: 3 plates")

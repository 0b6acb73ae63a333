"""Write the textures of scenes/tabletop.xml from scikit-image's sample images.

    .venv/bin/python scripts/make_tabletop_textures.py

Sources (scikit-image `skimage.data`, public-domain or CC0 images): astronaut
(NASA), brick, text, coffee, gravel. Each is written as an 8-bit sRGB PNG
into scenes/textures/, downsampled to at most 256 px on its long side (text kept at 448 px).
"""

from pathlib import Path

import numpy as np
from skimage import data
from skimage.io import imsave
from skimage.transform import resize

OUT = Path(__file__).resolve().parents[1] / "scenes" / "textures"


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    for name in ("astronaut", "brick", "text", "coffee", "gravel"):
        img = getattr(data, name)()
        s = (448 if name == "text" else 256) / max(img.shape[:2])
        if s < 1:
            img = resize(img, (round(img.shape[0] * s), round(img.shape[1] * s)), anti_aliasing=True,
                         preserve_range=True)
        imsave(OUT / f"{name}.png", np.clip(np.rint(img), 0, 255).astype(np.uint8), check_contrast=False)
        print(OUT / f"{name}.png", img.shape)


if __name__ == "__main__":
    main()

"""Write rendered RGB frames as an animated GIF or an MP4 video."""

from __future__ import annotations

from os import PathLike
from pathlib import Path
from typing import Iterable

import numpy as np

from magail_sumo.errors import MagailSumoError

FORMATS = (".gif", ".mp4")


def write_video(path: str | PathLike, frames: Iterable[np.ndarray], fps: int = 10) -> int:
    """Write (H, W, 3) uint8 frames to ``path`` (.gif or .mp4); returns the frame count.

    GIFs are written with Pillow; MP4 (H.264) with imageio's bundled ffmpeg.
    """
    p = Path(path)
    if p.suffix.lower() not in FORMATS:
        raise MagailSumoError(f"{p}: unsupported video format (use {' or '.join(FORMATS)})")
    p.parent.mkdir(parents=True, exist_ok=True)
    if p.suffix.lower() == ".gif":
        from PIL import Image

        images = [Image.fromarray(np.asarray(f, np.uint8)) for f in frames]
        if not images:
            raise MagailSumoError(f"{p}: no frames to write")
        images[0].save(p, save_all=True, append_images=images[1:], duration=int(1000 / fps),
                       loop=0, optimize=False)
        return len(images)
    import imageio.v2 as imageio

    n = 0
    with imageio.get_writer(p, fps=fps, codec="libx264", quality=7, macro_block_size=16) as out:
        for f in frames:
            out.append_data(np.asarray(f, np.uint8))
            n += 1
    if not n:
        raise MagailSumoError(f"{p}: no frames to write")
    return n

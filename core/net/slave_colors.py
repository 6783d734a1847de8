"""Each slave's colour, derived from its name so it stays the same across renders, restarts and
machines (never from the order in which slaves answer)."""
import colorsys
import hashlib

# 16 colours far enough apart to tell tiles apart: 8 hues, each bright and darker.
PALETTE = [colorsys.hsv_to_rgb(hue / 8, 0.75, value) for value in (0.95, 0.6) for hue in range(8)]


def slave_color(name: str) -> tuple:
    """An RGB colour (0..1) for a slave name."""
    digest = hashlib.blake2b(name.encode("utf-8"), digest_size=4).digest()
    return PALETTE[int.from_bytes(digest, "little") % len(PALETTE)]


def ansi_swatch(name: str) -> str:
    """The colour as a 24-bit terminal swatch, for command-line output."""
    r, g, b = (round(c * 255) for c in slave_color(name))
    return f"\033[48;2;{r};{g};{b}m  \033[0m"

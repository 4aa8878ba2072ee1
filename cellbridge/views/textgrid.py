"""The skin as a grid of character cells: pure layout for the terminal view.

A :class:`~cellbridge.views.model.Frame` and a size in characters in, rows of
``(char, fg_rgb, bg_rgb)`` out. Each element is a block of ``cw`` × ``ch`` characters
coloured by its level (its id in the corner when there is room), its label centred in it; each contact is a marker at its
estimated position (finer than the element) with its id beside it, moved to the nearest
place (in element units) where a blank keeps it apart from every element's id and label:
never ``↕02.1N`` read as one word. A skin on a robot is drawn patch by patch: each
patch's block with its link and name in the row above it. The layout's +y is
drawn up, as on the web page and in Foxglove. Cells never shrink below 4×1
characters: a skin that does not fit then grows the grid beyond the size given, and
the terminal view scrolls it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

from cellbridge.views.model import Frame, level_rgb

RGB = tuple[int, int, int]
MIN_W, MIN_H = 4, 1
MAX_W, MAX_H = 20, 8


@dataclass
class TextGrid:
    cw: int  # characters per element, across
    ch: int  # rows per element
    rows: list[list[tuple[str, RGB, RGB]]]

    def text(self) -> list[str]:
        return ["".join(c for c, _, _ in row) for row in self.rows]


def _ink(bg: RGB) -> RGB:
    """Black or white text, whichever reads on ``bg``."""
    lum = 0.299 * bg[0] + 0.587 * bg[1] + 0.114 * bg[2]
    return (0, 0, 0) if lum > 140 else (255, 255, 255)


def cell_size(rows: int, cols: int, width: int, height: int) -> tuple[int, int]:
    """(cw, ch): as large as fits, about twice as wide as tall (a terminal character is tall)."""
    if rows <= 0 or cols <= 0:
        return MIN_W, MIN_H
    ch = max(MIN_H, min(MAX_H, height // rows))
    cw = max(MIN_W, min(MAX_W, width // cols, 2 * ch + 4))
    return cw, ch


@lru_cache(maxsize=16)
def _offsets(cw: int, ch: int) -> list[tuple[int, int]]:
    """(row, column) moves within one element each way, nearest first in element units."""
    moves = [(dr, dc) for dr in range(-ch, ch + 1) for dc in range(-cw, cw + 1)]
    return sorted(moves, key=lambda m: ((m[0] / ch) ** 2 + (m[1] / cw) ** 2, abs(m[0]), abs(m[1])))


def _place(text: str, r0: int, c0: int, taken: set[tuple[int, int]], cw: int, ch: int, rows: int, cols: int
           ) -> tuple[int, int]:
    """Where to write a contact's ``text``: the place nearest (r0, c0) whose characters and
    the one on each side are not ``taken`` (ids, labels, other markers); (r0, c0) itself
    when there is none within an element's reach."""
    n = len(text)
    for dr, dc in _offsets(cw, ch):
        r, c = r0 + dr, c0 + dc
        if 0 <= r < rows and 0 <= c and c + n <= cols \
                and not any((r, x) in taken for x in range(c - 1, c + n + 1)):
            return r, c
    return r0, c0


def layout(frame: Frame, width: int, height: int) -> TextGrid:
    cw, ch = cell_size(frame.rows, frame.cols, width, height)
    bg0: RGB = (0, 0, 0)
    grid = [[(" ", (200, 200, 200), bg0) for _ in range(frame.cols * cw)] for _ in range(frame.rows * ch)]
    taken: set[tuple[int, int]] = set()  # characters of ids, labels and markers written so far
    for blk in frame.patches:  # a skin on a robot: each patch's link and name in the row above its block
        top = (frame.rows - 1 - (blk.row0 + blk.rows)) * ch
        if not 0 <= top < len(grid):
            continue
        room = (blk.cols + 1) * cw - 1  # its block and the gap after it
        title = blk.title if len(blk.title) <= room else blk.short  # the name alone when narrow
        title = title if len(title) <= room else title[: max(0, room - 1)] + "…"
        for i, chx in enumerate(title):
            x = blk.col0 * cw + i
            if x < len(grid[top]):
                grid[top][x] = (chx, (160, 180, 200), bg0)
                taken.add((top, x))
    for cell in frame.cells:
        bg = level_rgb(cell.level)
        ink = _ink(bg)
        top = (frame.rows - 1 - cell.row) * ch
        left = cell.col * cw
        gap_row = ch >= 3  # a blank line under each element when there is room, as the column on its right
        for r in range(ch):
            for c in range(cw):
                # a one-character gap on the right keeps neighbouring elements apart
                inside = c < cw - 1 and not (gap_row and r == ch - 1)
                grid[top + r][left + c] = (" ", ink, bg if inside else bg0)
        if gap_row and cw >= 6:  # the element's id in its corner
            for i, chx in enumerate(str(cell.bridge)[: cw - 2]):
                grid[top][left + i] = (chx, ink, bg)
                taken.add((top, left + i))
        label = cell.label[: cw - 1]
        r = top + (ch - 1) // 2 if not gap_row else top + max(1, (ch - 2) // 2)
        start = left + max(0, (cw - 1 - len(label)) // 2)
        for i, chx in enumerate(label):
            grid[r][start + i] = (chx, ink, bg)
            taken.add((r, start + i))
    for con in frame.contacts:
        if not (math.isfinite(con.col) and math.isfinite(con.row)):
            continue
        c = min(frame.cols * cw - 1, max(0, int(con.col * cw)))
        r = min(frame.rows * ch - 1, max(0, int((frame.rows - con.row) * ch)))
        ox, oy = con.observable
        mark = "●" if ox and oy else ("↔" if oy else ("↕" if ox else "✚"))
        text = mark + str(con.id)
        r, c = _place(text, r, c, taken, cw, ch, frame.rows * ch, frame.cols * cw)
        for i, chx in enumerate(text):
            if c + i < len(grid[r]):
                _, _, bg = grid[r][c + i]
                grid[r][c + i] = (chx, (255, 255, 255) if i == 0 else _ink(bg), bg)
                taken.add((r, c + i))
    return TextGrid(cw, ch, grid)

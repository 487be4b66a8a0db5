"""Progress bars on stderr (shown only when stderr is a terminal and not with -q; the
callers decide): a fit's stages, and the tile counts of a fit in tiles.
"""
from __future__ import annotations

import sys

import click


def stage_bar(length: int, label: str):
    """A click progress bar on stderr of `length` steps, showing each step's name."""
    return click.progressbar(length=length, label=label, file=sys.stderr, item_show_func=lambda s: s)


def caption(bar, text: str) -> None:
    """Show text beside a click progress bar without advancing it: bar.update(0, text)
    sets the text but draws nothing until the next step (a tiled fit's tile counts then
    never appeared)."""
    bar.current_item = text
    bar.render_progress()


def survey_progress(inputs, options, outputs: int, output=None):
    """A --seamless fit's progress bar on stderr and the core.plan.TiledRun callbacks that
    move it: for a survey fitted in tiles beyond --memory (c1mesh.pipeline.bounded_fit), its
    stages with each pass's tile count, as a single large input shows them; in memory, the
    outputs of -O as their tiles are written, or the stages of the one -o fit (output: its
    path or stream)."""
    from c1mesh.pipeline.driver import STAGES
    from c1mesh.pipeline.bounded_fit import TILED_STAGES
    from c1mesh.pipeline.run import in_tiles

    if in_tiles(list(inputs), options, output):
        progress = stage_bar(len(TILED_STAGES), "fitting survey")
        return progress, {"on_stage": lambda name: progress.update(1, name),
                          "on_tile": lambda name, done, tiles: caption(progress, f"{name}: tile {done} of {tiles}")}
    if outputs:
        progress = stage_bar(outputs, "tiles")
        return progress, {"on_output": lambda row: progress.update(1, row["tile"])}
    progress = stage_bar(len(STAGES), "fitting survey")
    return progress, {"on_stage": lambda name: progress.update(1, name)}

"""What c1mesh may print on stderr of a run that succeeded, for the tests that read it."""
from __future__ import annotations

import re

from c1mesh.stages.warnings import smoothing_suggestion

ADVICE = re.compile(r"c1mesh: note: .+?: " + re.escape(smoothing_suggestion(1, 1)).replace("100%", r"\d+%"))
"""The note advising --smooth auto for noisy heights (c1mesh.stages.warnings), any share,
after the input's name (a path, which may hold ':')."""

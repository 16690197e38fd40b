"""Measured-data study (issue 4): what the paper's simulation gets wrong, why, and the gain.

``study(manifest, report=..., figures_dir=...)`` is the API of ``clblur study``;
``study_groups`` runs on groups built from arrays (``pair_group``, ``stack_group``,
``series_groups``), e.g. virtual-camera data (``clblur.study.synthetic``).
"""

from clblur.study.effects import EFFECT_NAMES
from clblur.study.pairs import pair_group
from clblur.study.run import StudyResult, study, study_groups
from clblur.study.series import series_groups
from clblur.study.stacks import stack_group

__all__ = ["EFFECT_NAMES", "StudyResult", "pair_group", "series_groups", "stack_group",
           "study", "study_groups"]

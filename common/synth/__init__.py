"""Synthetic fresco with ground truth (issue 5): paint, relieve, break, deteriorate, cut out.

``generate_wall(..., preset="pompeii")`` makes walls that look like real broken Pompeii frescoes
(:mod:`common.synth.realistic`, issue 15); :mod:`common.synth.stats` measures real and synthetic
collections with the same code.

Public API: :func:`generate_wall` -> :class:`Wall` (fragments with RGBN images, surfaces and
poses; adjacency with shared crack length; contour correspondences), :func:`save_groundtruth` /
:func:`load_groundtruth` (schema ``tessera.groundtruth``) and :func:`import_dafne`.
"""

from common.synth.wall import Fragment, Wall, generate_wall, pose_apply
from common.synth.groundtruth import label_patch_pairs, load_groundtruth, save_groundtruth

__all__ = ["Fragment", "Wall", "generate_wall", "pose_apply", "save_groundtruth", "load_groundtruth",
           "label_patch_pairs", "import_dafne"]


def __getattr__(name):
    if name == "import_dafne":
        from common.synth.dafne import import_dafne
        return import_dafne
    raise AttributeError(name)

"""Matcher: learned multi-cue matching, ranked proposals, 2-D alignment, online learning (thesis §5).

See ``docs/matching.md``. Entry points: :func:`common.matching.pairs.training_set`,
:func:`common.matching.classifiers.make_classifier`,
:func:`common.matching.evaluation.grouped_cross_validation`, :class:`common.matching.index.MatchIndex`,
:func:`common.matching.alignment.align_fragments`, :class:`common.matching.proposals.ProposalStore`,
:func:`common.matching.models.save_model` / :func:`~common.matching.models.load_model`.
"""

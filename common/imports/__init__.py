"""Importing what a lab already has on disk: checked at the door, content-keyed, resumable.

* :mod:`.driver` -- :func:`run_import`, :class:`ImportItem`, :class:`Output`, :class:`StoreSink`,
  :class:`Ledger`, :class:`ImportSummary`, :class:`ImportRefused` (the shared driver of every
  ``tessera import`` kind), :func:`load_sources` / :func:`source_conflict` (its check of the files imported
  before, also made by ``tessera ps --store``);
* :mod:`.progress` -- :class:`ProgressBar`.

Documented for users in ``docs/import.md``.
"""

from common.imports.driver import (ImportItem, ImportRefused, ImportSummary, Ledger, Output, StoreSink, item_key,
                                   load_sources, run_import, source_conflict)
from common.imports.progress import ProgressBar

__all__ = ["ImportItem", "ImportRefused", "ImportSummary", "Ledger", "Output", "ProgressBar", "StoreSink",
           "item_key", "load_sources", "run_import", "source_conflict"]

"""Feature extractor: per-fragment and per-patch descriptors (Toler-Franklin 2011, §5.2.1, §5.4).

``extract_features(image) -> FeatureTable``; ``save_features`` / ``load_features`` store tables as
``tessera.features`` artifacts; :mod:`common.features.registry` declares every descriptor.
"""

from common.features.registry import (DESCRIPTORS, Descriptor, correspondence, fragment_descriptors,
                                      patch_descriptors)
from common.features.table import (FeatureTable, extract_features, load_features, read_features,
                                   save_features, write_features)

__all__ = ["DESCRIPTORS", "Descriptor", "correspondence", "fragment_descriptors", "patch_descriptors",
           "FeatureTable", "extract_features", "load_features", "save_features", "read_features",
           "write_features"]

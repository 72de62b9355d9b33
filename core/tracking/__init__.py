"""Analysis-by-synthesis tracking: the single-frame fit, its compiled cost, the per-sequence
tracker."""

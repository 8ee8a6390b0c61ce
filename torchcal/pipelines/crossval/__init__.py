"""Cross-validated comparison of fitted candidates: what every fit of a data set shares, a candidate
fitted on all rows and cross-validated from that fit, priors and their scales, and the scores and rule
that decide. The loop compares its candidates with it; ``calibrate`` chooses its prior on small data
with it (and so does not reach into the loop)."""

"""Template cloud P from the first frame (Su et al. 2019, section II.A): features,
matching, camera pairs, the link gate."""

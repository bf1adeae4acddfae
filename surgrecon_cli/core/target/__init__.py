"""Target cloud G of a frame (Su et al. 2019, section II.B): 2D tracking of the template
points and their triangulation."""

"""The reactive merge world (kinematic bicycles, IDM/MOBIL drivers that yield) and its interaction dataset."""

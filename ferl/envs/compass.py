"""The four compass moves that both worlds of the dissertation offer (Figs. 3.1, 4.2): N E S W."""

ACTIONS = ("N", "E", "S", "W")
N, E, S, W = range(len(ACTIONS))

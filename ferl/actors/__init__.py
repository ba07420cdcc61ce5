"""Actors: choose actions from the agent's state and learn from TD errors (``ferl.interfaces.Actor``).

``free_energy``: the FERL actor of the dissertation (§3.2); ``td``: the one online TD step that
every trainer takes with any actor.
"""

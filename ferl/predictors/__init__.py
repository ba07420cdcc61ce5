"""Predictors: recurrent models of the history whose memory the actor sees (``ferl.interfaces.Predictor``).

``heads``: what any predictor predicts from its memory, its errors and the heads' BPTT; ``elman``:
the Elman memory of chapters 4–5; ``training``: pattern-mode BPTT of predictors batched over runs.
"""

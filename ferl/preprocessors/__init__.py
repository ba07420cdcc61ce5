"""Preprocessors: map raw observations to what the predictors and the actor see (``ferl.interfaces.Preprocessor``).

``rbm``: chapter 5's RBM trained by contrastive divergence; ``cache``: fits kept on disk.
"""

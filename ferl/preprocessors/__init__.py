"""Preprocessors: map raw observations to what the predictors and the actor see (``ferl.interfaces.Preprocessor``).

``rbm``: chapter 5's RBM trained by contrastive divergence; ``gaussian_rbm``: the same with Gaussian
visible units for continuous observations (§5.4 "Fifth"); ``dbn``: a deep belief network, RBMs
stacked and trained greedily (§5.4 "Second"); ``cache``: fits kept on disk.
"""

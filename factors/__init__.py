"""fgnav.factors: the custom GTSAM factors of fgnav (one module per measurement model).

Each module has a pure numpy ``*_error(...) -> (error, jacobians)`` function and a constructor
returning a ``gtsam.CustomFactor``. Import as ``fgnav.factors``.
"""

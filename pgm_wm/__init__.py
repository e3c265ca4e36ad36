"""pgm_wm: probabilistic world models, built up chapter by chapter.

Modules, in the order the book introduces them:

* :mod:`pgm_wm.gaussian`     dense Gaussian algebra (marginalize, joint, condition)   — Chapter 1
* :mod:`pgm_wm.kalman`       Kalman filter, log-likelihood, RTS smoother              — Chapter 1
* :mod:`pgm_wm.aggregation`  Bayesian aggregation and set conditioning                — Chapter 2
* :mod:`pgm_wm.factorized`   the RKN's factorized belief                              — Chapter 3
* :mod:`pgm_wm.rkn`          Recurrent Kalman Network                                  — Chapter 3
* :mod:`pgm_wm.acrkn`        action-conditional RKN                                    — Chapter 4
* :mod:`pgm_wm.hiprssm`      hidden-parameter RSSM                                     — Chapter 5
* :mod:`pgm_wm.mts3`         multi-time-scale SSM                                      — Chapter 6
* :mod:`pgm_wm.datasets`     the bundled datasets and their simulators

Submodules are imported explicitly (``from pgm_wm.kalman import kalman_filter``) so that
importing the package stays cheap.
"""

__version__ = "0.1.0"

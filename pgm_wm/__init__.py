"""pgm_wm: probabilistic world models, built up chapter by chapter.

Modules, in the order the book introduces them:

* :mod:`pgm_wm.gaussian`     dense Gaussian algebra (marginalize, joint, condition)   — Chapter 1
* :mod:`pgm_wm.kalman`       Kalman filter, log-likelihood, RTS smoother              — Chapter 1
* :mod:`pgm_wm.aggregation`  Bayesian aggregation and set conditioning                — Chapter 2
* :mod:`pgm_wm.context`      context sets of transitions and a set-model fit loop     — Chapter 2
* :mod:`pgm_wm.factorized`   the RKN's factorized belief                              — Chapter 3
* :mod:`pgm_wm.rkn`          Recurrent Kalman Network                                  — Chapter 3
* :mod:`pgm_wm.encoders`     convolutional image trunk                                 — Chapter 3
* :mod:`pgm_wm.rnn_filters`  LSTM/GRU filtering baselines and the filter fit loop      — Chapter 3
* :mod:`pgm_wm.acrkn`        action-conditional RKN, control models, inverse dynamics  — Chapter 4
* :mod:`pgm_wm.training`     fit loop, imputation masks, multi-step prediction         — Chapter 4
* :mod:`pgm_wm.metrics`      RMSE, Gaussian NLL, sliding-window metrics, (de)normalize — Chapters 4, 6
* :mod:`pgm_wm.baselines`    RKN with actions as observations, LSTM, GRU, FFNN, Transformer
* :mod:`pgm_wm.hiprssm`      hidden-parameter RSSM                                     — Chapter 5
* :mod:`pgm_wm.mts3`         multi-time-scale SSM                                      — Chapter 6
* :mod:`pgm_wm.layers`       small shared network blocks (MLP)
* :mod:`pgm_wm.plotting`     plot and table helpers for the notebooks
* :mod:`pgm_wm.datasets`     the bundled datasets and their simulators

Submodules are imported explicitly (``from pgm_wm.kalman import kalman_filter``) so that
importing the package stays cheap.
"""

__version__ = "0.1.0"

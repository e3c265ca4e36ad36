"""pgm_wm: probabilistic world models, built up chapter by chapter.

Modules, in the order the book introduces them:

* :mod:`pgm_wm.beliefs`          the belief family: dense ``Gaussian``, ``DiagGaussian``, ``FactorizedBelief``
* :mod:`pgm_wm.filtering`        ``FilterResult`` (every filter's output) and the reference filter loop
* :mod:`pgm_wm.gaussian`         dense Gaussian algebra (marginalize, joint, condition)        — Chapter 1
* :mod:`pgm_wm.kalman`           Kalman predict/update, filter, RTS smoother                   — Chapter 1
* :mod:`pgm_wm.kalman_parallel`  parallel-in-time Kalman filter and smoother (associative scan) — Chapter 1
* :mod:`pgm_wm.lgssm`            ``LinearGaussianSSM`` parameters and ``fit_mle``              — Chapter 1
* :mod:`pgm_wm.aggregation`      Bayesian aggregation, set updates, set encoders               — Chapter 2
* :mod:`pgm_wm.context`          context sets of transitions, set-model fitting and scoring    — Chapter 2
* :mod:`pgm_wm.factorized`       the RKN's factorized steps and filters (reference + fast)     — Chapter 3
* :mod:`pgm_wm.rkn`              Recurrent Kalman Network: transitions, encoder, decoder, causes — Chapter 3
* :mod:`pgm_wm.encoders`         convolutional image trunk                                      — Chapter 3
* :mod:`pgm_wm.rnn_filters`      LSTM/GRU filtering baselines                                   — Chapter 3
* :mod:`pgm_wm.acrkn`            action-conditional RKN: control causes, readout, inverse model — Chapter 4
* :mod:`pgm_wm.hiprssm`          hidden-parameter RSSM: the task cause                          — Chapter 5
* :mod:`pgm_wm.mts3`             multi-time-scale SSM with N task levels                        — Chapter 6
* :mod:`pgm_wm.planning`         LQR as inference (Kalman duality), CEM/MPPI planning, closed loops — Chapter 7
* :mod:`pgm_wm.training`         the one ``fit`` loop, observation masks, the one loss factory
* :mod:`pgm_wm.evaluation`       multi-step / open-loop evaluation, window-wise scores
* :mod:`pgm_wm.metrics`          RMSE, Gaussian NLL, sliding-window metrics, (de)normalization
* :mod:`pgm_wm.baselines`        reference rows and competitors with the world-model interface
* :mod:`pgm_wm.builders`         every chapter's models with the notebooks' defaults
* :mod:`pgm_wm.layers`           shared network blocks (MLP, Gaussian head, positive maps)
* :mod:`pgm_wm.testing`          oracles shared by the tests and the notebooks' checks
* :mod:`pgm_wm.plotting`         plot and table helpers for the notebooks
* :mod:`pgm_wm.diagrams`         the models drawn by code (RKN cell, factorized covariance, MTS3, 1-D gain)
* :mod:`pgm_wm.datasets`         bundled datasets, their simulators and oracles, windows, ``SequenceData``
* :mod:`pgm_wm.experiments`      multi-seed experiments of the model chapters (``python -m pgm_wm.experiments``)

Submodules are imported explicitly (``from pgm_wm.kalman import kalman_filter``) so that
importing the package stays cheap.
"""

__version__ = "0.2.0"

"""The chapters' experiments: which data, which models, which protocol.

Each function returns a :class:`pgm_wm.experiments.runner.Experiment`; the command line
(``python -m pgm_wm.experiments NAME``) runs it for several seeds and writes ``results/NAME.json``.
Model sizes are the chapters' notebook defaults; the budget per model is set on the command line.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Callable

from torch import nn

from ..acrkn import AcRKN, MLPControl, NormBoundedTransition, difference_scaling
from .. import baselines
from ..baselines import FFNNBaseline, GRUBaseline, LSTMBaseline, RKNActionsAsObs
from ..datasets import load
from ..rkn import BeliefDecoder, LocallyLinearTransition, ObservationEncoder
from .runner import Experiment, ModelSpec, Protocol, Splits

__all__ = ["EXPERIMENTS", "ch4_experiment"]


@lru_cache(maxsize=None)
def _splits(name: str) -> Splits:
    return Splits(*(load(name, s) for s in ("train", "valid", "test")))


def _reference_models() -> dict[str, ModelSpec]:
    """The reference rows every results table has (fitted in closed form on the training split)."""
    def normalized_train(s: Splits):
        return s.normalized("train")

    return {
        "repeat last": ModelSpec(lambda s: baselines.RepeatLast.fit(normalized_train(s)[0], normalized_train(s)[2]), trained=False),
        "training mean": ModelSpec(lambda s: baselines.TrainingMean.fit(normalized_train(s)[0], normalized_train(s)[2]),
                                   trained=False),
        "linear ARX (order 5)": ModelSpec(lambda s: baselines.LinearARX.fit(*normalized_train(s)[:2], order=5,
                                                                  valid=normalized_train(s)[2]), trained=False),
    }


def _acrkn(s: Splits, m: int = 15, bounded: bool = False, differences: bool = True) -> nn.Module:
    do, da = s.train.obs_dim, s.train.action_dim
    shift, scale = difference_scaling(s.train.stats)
    transition: nn.Module = LocallyLinearTransition(m, 15, 3)
    if bounded:
        transition = NormBoundedTransition(transition, max_norm=1.0)
    return AcRKN(ObservationEncoder(do, m, (64,)), transition, MLPControl(da, m, (64, 64)),
                 BeliefDecoder(m, do, (64,), (64,)), predict_differences=differences,
                 diff_shift=shift, diff_scale=scale)


def ch4_experiment(dataset: str = "hysteresis_arm") -> Experiment:
    """Chapter 4: ac-RKN variants (difference / absolute readout, norm-bounded A) against the
    RKN with actions as observations, LSTM, GRU, FFNN and the reference rows; open-loop
    prediction 1–50 steps after a 50-step context."""

    def readout(s: Splits) -> dict:
        shift, scale = difference_scaling(s.train.stats)
        return dict(diff_shift=shift, diff_scale=scale)

    def dims(s: Splits) -> tuple[int, int]:
        return s.train.obs_dim, s.train.action_dim

    models: dict[str, ModelSpec] = {
        "ac-RKN (difference readout)": ModelSpec(lambda s: _acrkn(s)),
        "ac-RKN (absolute readout)": ModelSpec(lambda s: _acrkn(s, differences=False)),
        "ac-RKN, ‖A‖≤1": ModelSpec(lambda s: _acrkn(s, bounded=True)),
        "RKN (actions as obs.)": ModelSpec(lambda s: RKNActionsAsObs(*dims(s), 15, 15, 3, (64,), (64,), **readout(s))),
        "LSTM": ModelSpec(lambda s: LSTMBaseline(*dims(s), 64, (64,), (64,), **readout(s))),
        "GRU": ModelSpec(lambda s: GRUBaseline(*dims(s), 64, (64,), (64,), **readout(s))),
        "FFNN": ModelSpec(lambda s: FFNNBaseline(*dims(s), window=5, hidden=(64, 64), **readout(s))),
    }
    models.update(_reference_models())
    protocol = Protocol(context_len=50, horizon=50, horizons=(1, 5, 10, 25, 50), eval_stride=50,
                        valid_stride=100, batch_size=32, keep_prob=0.25, open_loop_prob=0.5, patience=None)
    return Experiment(f"ch4_{dataset}", f"Chapter 4, open-loop prediction on {dataset}", lambda: _splits(dataset),
                      models, protocol, units="mrad", scale=1e3)


EXPERIMENTS: dict[str, Callable[[], Experiment]] = {
    "ch4": ch4_experiment,
}

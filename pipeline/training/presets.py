"""Named training presets: the paper's set-ups × encoder × recipe, as typed configs.

A :class:`TrainingPreset` ties together what one training run needs: the dataset
(:class:`~pipeline.training.datasets.DatasetConfig`), the model (:class:`EstimatorConfig`), the optimiser
(:class:`~pipeline.training.trainer.TrainConfig`) and the loss weights
(:class:`~pipeline.training.kinetic.KineticWeights`). Names are resolved here and only here
(:func:`get_preset`); library code passes the typed objects.

Set-ups (paper, section "Training"):

=================  ==========================  ===  =====  =====  ===  ======  =====  ======
preset             data                        D    L      hid.   E    iters   batch  noise σ
=================  ==========================  ===  =====  =====  ===  ======  =====  ======
vehicle            vehicle-dropout (1.5 M pts) 2    10     4      4    10,000  2,048  0 (*)
vehicle-sparse     vehicle-sparse (~1,500 pts) 2    4      4      4    5,000   128    0 (*)
sir-single         sir-single                  3    10     6      6    10,000  2,048  0.01
sir-multi          sir-multi                   3    10     6      6    10,000  2,048  0.01
sir-joint          sir-multi, S,I,R,β,γ        5    10     6      6    10,000  2,048  0.01
sir-sf-joint       sir-sf, S,I,R,β,γ           5    10     6      6    10,000  2,048  0 (**)
=================  ==========================  ===  =====  =====  ===  ======  =====  ======

All: R = 5 observations per window, Adam at constant lr 1e-3 (paper recipe), forward direction
unless overridden. Context rows: the observed values and ``t_obs - t_target``; the vehicle set-ups
also get the absolute time ``t_obs`` (4 channels; ``pipeline.training.datasets`` explains why). (*) Vehicle
context noise: the paper's one sentence "adding Gaussian noise with σ = 1.0" is what
``pipeline.systems.vehicle`` already uses as the *observation* noise of the positions (the paper
gives no other observation noise for the vehicle), so the stored contexts already carry it; adding
it again in training would feed the model σ = √2 contexts while it is evaluated on σ = 1 ones. For
SIR the paper states the observation noise (0.027) and the context noise (0.01) separately, so there
both apply. (**) ``sir-sf-joint`` is the product's preset, not the paper's: the ``sir-sf`` prior
(``pipeline.systems.sir``) fitted to the San Francisco series, whose observation noise (5e-4) is the
only noise; the paper's context noise of 0.01 would be 20× the data's scatter and drown its I
(median 8e-4). Its flow also works in the SIR log-ratio coordinates
(``EstimatorConfig.target_transform = "sir-log-ratio"``: u = log(I/S), log(R/S), log β, log γ, so
D_flow = 4; ``pipeline.models.target_transforms``): every draw is then on the simplex with
β, γ > 0 by construction. Trained in raw coordinates, its draws had negative I in ~30 % of the
weekly forecast's sample rows and β < 0 in ~6 %. The paper presets keep the identity (their tables
are the paper's, in raw coordinates).

Encoders: ``mlp``, ``transformer``, ``transformer-ke`` (the transformer trained with the kinetic
terms: λ1 = 1, λ2 = :data:`KE_PATH_LENGTH`, λ3 = :data:`KE_INTERMEDIATE_NLL`, see below) and
``mamba``, with the encoder package's default sizes (transformer d_model 32, 4 + 4 layers,
feed-forward 64, dropout 0; Mamba as ``MambaEncoderConfig`` defaults).

Recipes:

* ``paper``: exactly the paper's optimiser settings above, validation every 100 iterations, no
  early stop.
* ``fast`` (default): our recipe, chosen by measurement (docs/training.md, bench/training.py):
  batch 512, warm-up + cosine schedule to a 3× higher peak lr over 60 % of the paper's
  iterations, and early stop once the validation NLL stops improving; same model sizes. The
  batch-2048 step is dominated by the encoder (~90 % of the time for the transformer), so a 4×
  smaller batch makes each step ~3.5× cheaper, while the extra gradient noise is absorbed by the
  decaying schedule.

Kinetic weights for ``transformer-ke`` (the paper gives none): λ2 = 0.01 and λ3 = 0.001.
Measured on sir-multi (standardized units) after 1,200 iterations: NLL −8.2, mean per-layer
path length 5.6, intermediate NLL 383 (f_1 … f_{L-1} scored under the *conditional* base, which
narrows to the target's small spread given the window). The weighted terms then add ≈ 0.06 and
≈ 0.4 nats to a loss whose NLL moves by ~13 nats in training: they shape the paths without
dominating the likelihood (docs/training.md).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TypeGuard

from pipeline.errors import ConfigError
from pipeline.models.encoders import EncoderConfig, EncoderKind
from pipeline.models.estimator import EstimatorConfig, make_estimator_config
from pipeline.names import ENCODER_CHOICES, RECIPES, TRAINING_SETUPS, EncoderChoice, Recipe
from pipeline.training.datasets import DatasetConfig
from pipeline.training.kinetic import KineticWeights
from pipeline.training.trainer import TrainConfig

# The encoder each choice builds: transformer-ke is the transformer trained with kinetic terms.
_ENCODER_KIND: dict[EncoderChoice, EncoderKind] = {"mlp": "mlp", "transformer": "transformer",
                                                   "transformer-ke": "transformer",
                                                   "mamba": "mamba"}
DEFAULT_RECIPE: Recipe = "fast"

KE_PATH_LENGTH = 0.01
KE_INTERMEDIATE_NLL = 0.001

# Fast recipe levers (measured; docs/training.md "Recipes").
FAST_BATCH_SIZE = 512
FAST_LR = 3e-3
FAST_WARMUP_FRACTION = 0.05
FAST_FINAL_LR_FRACTION = 0.01
FAST_ITERATION_FRACTION = 0.6  # of the paper's iterations; the cosine schedule spans them
FAST_EARLY_STOP_PATIENCE = 15  # evaluations (of every 100 iterations) without improvement
# The product's joint model reads two weeks of the S/I/R series (docs/models.md).
SF_WAVES_WINDOW = 14


@dataclass(frozen=True)
class SetUp:
    """The paper-level description of one preset (before encoder and recipe are chosen)."""

    name: str
    dataset: str
    target: str
    features: int
    context_channels: int
    layers: int
    hidden_features: int
    embedding_features: int
    iterations: int
    batch_size: int
    lr: float
    context_noise_sigma: float
    window: int = 5
    target_transform: str = "identity"
    context_transform: str = "identity"


SETUPS: dict[str, SetUp] = {s.name: s for s in (
    SetUp("vehicle", "vehicle-dropout", "state", 2, 4, 10, 4, 4, 10_000, 2048, 1e-3, 0.0),
    SetUp("vehicle-sparse", "vehicle-sparse", "state", 2, 4, 4, 4, 4, 5_000, 128, 1e-3, 0.0),
    SetUp("sir-single", "sir-single", "state", 3, 4, 10, 6, 6, 10_000, 2048, 1e-3, 0.01),
    SetUp("sir-multi", "sir-multi", "state", 3, 4, 10, 6, 6, 10_000, 2048, 1e-3, 0.01),
    SetUp("sir-joint", "sir-multi", "state+params", 5, 4, 10, 6, 6, 10_000, 2048, 1e-3, 0.01),
    SetUp("sir-sf-joint", "sir-sf", "state+params", 5, 4, 10, 6, 6, 10_000, 2048, 1e-3, 0.0,
          target_transform="sir-log-ratio"),
    SetUp("sf-waves-joint", "sf-waves", "state+params", 4, 4, 5, 64, 32, 5_000, 2048, 1e-3,
          0.0, window=SF_WAVES_WINDOW, target_transform="sir-log-ratio",
          context_transform="sir-log-infectious"),
)}


@dataclass(frozen=True)
class TrainingPreset:
    """One fully specified training run."""

    name: str
    encoder_choice: EncoderChoice
    recipe: Recipe
    dataset: DatasetConfig
    estimator: EstimatorConfig
    train: TrainConfig
    kinetic: KineticWeights

    @property
    def run_name(self) -> str:
        return (f"{self.name}-{self.dataset.direction}-{self.encoder_choice}-"
                f"{self.backend}-{self.recipe}")

    @property
    def backend(self) -> str:
        """The flow package (``zuko`` or ``nflows``)."""
        flow = self.estimator.flow
        if flow is None:  # EstimatorConfig.__post_init__ always sets it
            raise ConfigError(f"preset {self.name!r}: its estimator config has no flow config")
        return flow.backend

    def with_overrides(self, *, iterations: int | None = None, batch_size: int | None = None,
                       lr: float | None = None, seed: int | None = None,
                       num_threads: int | None = None) -> TrainingPreset:
        """A copy with optimiser overrides (None = keep). The seed seeds the batches."""
        changes = {k: v for k, v in dict(iterations=iterations, batch_size=batch_size, lr=lr,
                                         seed=seed, num_threads=num_threads).items()
                   if v is not None}
        return dataclasses.replace(self, train=dataclasses.replace(self.train, **changes))

    def to_dict(self) -> dict[str, object]:
        return {"name": self.name, "encoder_choice": self.encoder_choice, "recipe": self.recipe,
                "dataset": dataclasses.asdict(self.dataset),
                "estimator": dataclasses.asdict(self.estimator),
                "train": dataclasses.asdict(self.train),
                "kinetic": dataclasses.asdict(self.kinetic)}


def _encoder_config(choice: EncoderChoice, embedding: int) -> EncoderConfig:
    """The encoder package's default sizes for both recipes: a narrower transformer (d_model 16)
    made steps 25 % cheaper but learned so much slower per step that it lost (docs/training.md)."""
    return EncoderConfig(kind=_ENCODER_KIND[choice], embedding_features=embedding)


def _kinetic(choice: EncoderChoice) -> KineticWeights:
    if choice == "transformer-ke":
        return KineticWeights(nll=1.0, path_length=KE_PATH_LENGTH,
                              intermediate_nll=KE_INTERMEDIATE_NLL)
    return KineticWeights()


def train_config(setup: SetUp, recipe: Recipe, seed: int = 0) -> TrainConfig:
    """The optimiser settings of ``recipe`` for ``setup``."""
    if recipe == "paper":
        return TrainConfig(iterations=setup.iterations, batch_size=setup.batch_size,
                           lr=setup.lr, schedule="constant",
                           context_noise_sigma=setup.context_noise_sigma, seed=seed)
    # Fast: a smaller batch (never larger than the paper's: vehicle-sparse keeps 128), a higher
    # peak lr with warm-up and cosine decay over 60 % of the paper's iterations, plateau stop.
    batch = min(FAST_BATCH_SIZE, setup.batch_size)
    return TrainConfig(iterations=max(1, round(setup.iterations * FAST_ITERATION_FRACTION)),
                       batch_size=batch, lr=FAST_LR, schedule="cosine",
                       warmup_fraction=FAST_WARMUP_FRACTION,
                       final_lr_fraction=FAST_FINAL_LR_FRACTION,
                       early_stop_patience=FAST_EARLY_STOP_PATIENCE,
                       context_noise_sigma=setup.context_noise_sigma, seed=seed)


def get_preset(name: str, encoder: str = "transformer", *, recipe: str = DEFAULT_RECIPE,
               backend: str | None = None, direction: str = "forward", seed: int = 0,
               dataset_seed: int = 0, n_trajectories: int | None = None) -> TrainingPreset:
    """Resolve a preset by name. ``backend`` None = the flow package's default backend."""
    if name not in SETUPS:
        raise ConfigError(f"unknown preset {name!r}; known: {list(TRAINING_SETUPS)}")
    if not _is_encoder_choice(encoder):
        raise ConfigError(f"unknown encoder {encoder!r} for preset {name!r}; "
                          f"choose one of {list(ENCODER_CHOICES)}")
    if not _is_recipe(recipe):
        raise ConfigError(f"unknown recipe {recipe!r}; choose one of {list(RECIPES)}")
    setup = SETUPS[name]
    dataset = DatasetConfig(name=setup.dataset, direction=direction, target=setup.target,
                            window=setup.window, seed=dataset_seed,
                            n_trajectories=n_trajectories)
    flow_options: dict[str, object] = {"layers": setup.layers,
                                       "hidden_features": setup.hidden_features}
    if backend is not None:
        flow_options["backend"] = backend
    estimator = make_estimator_config(setup.features, setup.context_channels, setup.window,
                                      _encoder_config(encoder, setup.embedding_features),
                                      absolute_time=bool(dataset.absolute_time),
                                      target_transform=setup.target_transform,
                                      context_transform=setup.context_transform, **flow_options)
    return TrainingPreset(name=name, encoder_choice=encoder, recipe=recipe, dataset=dataset,
                          estimator=estimator, train=train_config(setup, recipe, seed),
                          kinetic=_kinetic(encoder))


def _is_encoder_choice(name: str) -> TypeGuard[EncoderChoice]:
    return name in ENCODER_CHOICES


def _is_recipe(name: str) -> TypeGuard[Recipe]:
    return name in RECIPES

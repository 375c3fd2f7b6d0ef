"""Can label-free features of the registered pair predict where the answer is wrong, and does the sampled std keep it?

The calibration's residual term (``monai_probreg.uncertainty.residual``) widens the posterior where the registered
images stay unlike; held out, its std ranks the errors at Spearman 0.344 per component on the population probe but
0.163 on the subject probe (synthetic subjects registered by the whole command; issue "An uncertainty that belongs to
the answer" asks >= 0.30). A scratch look at that probe's cases found other signals of the pair: the errors are larger
where the answer's displacement bends (the local mean of its squared Laplacian) and where the network's own variance
is small. This study fits an error model of such features and scores it as the calibration's extra variance term:

- the features, per voxel of the model grid (:func:`pair_features`, :data:`FEATURES`): the pair's residual (the
  shipped form, and over 3- and 15-voxel boxes), the squared Laplacian of the refined mean velocity (upsampled) and of
  the deformable displacement (over 5-, 9- and 15-voxel boxes), the network's velocity variance, the displacement's
  length, the fixed image's gradient magnitude (over a 9-voxel box), all as logs, and the distance to the fixed
  image's edge and its intensity;
- the model: least squares of ``log |error|^2`` (mm^2, components summed) on the features and a constant, fitted on
  synthetic subjects of other training templates than the subject probe's (``--fit-templates`` of them, seeds far
  from the probe's): never a case it is scored on;
- its prediction ``exp(features . coef)`` on the model grid, averaged onto the velocity grid, replaces the residual in
  the calibration's term, scaled pair by pair to the residual's mean (the sidecar's weight stays in the regime it was
  fitted in; a product would fit the weight, and then coverage, by the single refit command);
- scored at the shipped calibration, nothing refitted: Spearman(std, |error|) per component on the subject probe's 6
  templates and the population probe's 6 validation subjects (the calibration's seeds), each with the std of 16
  samples (what the product's map is) and the posterior's own std without sampling (the calibrated velocity std
  upsampled to the image grid: what the samples estimate, up to the integration's damping, which does not change a
  ranking); and the label entropy's AUROC for wrongly propagated voxels on the validation subjects' real pairs
  (``benchmarks/uncertainty_calibration.py``'s ``label_case``).

    PYTHONPATH=benchmarks python experiments/error_model.py --threads 2   # ~12 min

Prints a table and writes ``experiments/results/error_model.json``. The product's error model
(:mod:`monai_probreg.uncertainty.error_model`, bundle 0.33.0) computes the first set's features with torch on the
image grid and is fitted and scored by the refit command and ``benchmarks/uncertainty_calibration.py``.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import uncertainty_calibration
from monai.data import Dataset
from scipy import ndimage
from study_setup import finish_study, population_probe_cases, study_parser, study_start
from uncertainty_calibration import label_case

import monai_probreg.fitting.population_probe as population_probe
import monai_probreg.registration.network as registration_network
from monai_probreg.data.dataset import labelled_pairs
from monai_probreg.engines.registration import register_pair
from monai_probreg.fitting.calibration_probes import SUBJECT_PROBE_TEMPLATES
from monai_probreg.fitting.population_probe import SEED_STRIDE, VOXELS_PER_CASE, PairPosterior, sampled_case_errors
from monai_probreg.fitting.subject_probe import SUBJECT_SEED, registered_case, subject_case, subject_errors
from monai_probreg.losses.lncc import box_sum
from monai_probreg.metrics.calibration import interval_z, spearman
from monai_probreg.registration.model import load_model
from monai_probreg.uncertainty.calibration import POSTERIOR_SAMPLES, Calibration, fit_calibration
from monai_probreg.uncertainty.error_model import squared_laplacian
from monai_probreg.uncertainty.residual import residual_variance
from monai_probreg.utils.tensors import plain_tensor

RESULTS = Path(__file__).resolve().parent / "results"
FEATURES = (
    "log residual",
    "log residual, 3-voxel box",
    "log residual, 15-voxel box",
    "log squared Laplacian of the mean velocity",
    "log squared Laplacian of the displacement, 5-voxel box",
    "log squared Laplacian of the displacement, 9-voxel box",
    "log squared Laplacian of the displacement, 15-voxel box",
    "log network velocity variance",
    "log displacement length",
    "log fixed gradient magnitude, 9-voxel box",
    "distance to the fixed image's edge",
    "fixed intensity",
)
FIT_SEED = SUBJECT_SEED + 500  # the fit's synthetic subjects: seeds far from the subject probe's
EDGE_LEVEL = 0.02  # the fixed image's edge: where its intensity (network input, in [0, 1]) falls below this
INSIDE_WINDOW = 15  # the torch features' stand-in for the edge distance: the foreground's fraction in this box
LOG_FLOOR = 1e-12  # added inside every log (an empty residual, a straight field)
SQUARED_ERROR_FLOOR = 1e-6  # mm^2, inside the fitted log of the squared error


def _laplacian_energy(field: np.ndarray, window: int) -> np.ndarray:
    """(C, *S) -> the squared Laplacian summed over components, averaged over a ``window``-voxel box."""
    energy = sum(ndimage.laplace(c.astype(np.float64)) ** 2 for c in field)
    return ndimage.uniform_filter(energy, window) if window > 1 else energy


def pair_features(warped, fixed, mean, log_var, displacement) -> np.ndarray:
    """(len(FEATURES), *S) on the model grid of one registered pair: ``warped``, ``fixed`` (1, 1, *S) network inputs,
    ``mean``, ``log_var`` (1, 3, *V) the refined posterior, ``displacement`` (1, 3, *S) its mean's."""
    size, grid = tuple(fixed.shape[2:]), tuple(mean.shape[2:])

    def up(x: torch.Tensor) -> np.ndarray:
        return F.interpolate(x.float(), size=size, mode="trilinear")[0, 0].numpy().astype(np.float64)

    image = fixed[0, 0].numpy().astype(np.float64)
    field = displacement[0].numpy()
    logged = [
        up(residual_variance(warped, fixed, grid)),
        up(residual_variance(warped, fixed, grid, window=3)),
        up(residual_variance(warped, fixed, grid, window=15)),
        up(torch.from_numpy(_laplacian_energy(mean[0].numpy(), 1))[None, None]),
        _laplacian_energy(field, 5),
        _laplacian_energy(field, 9),
        _laplacian_energy(field, 15),
        up(log_var.exp().mean(1, keepdim=True)),
        np.linalg.norm(field, axis=0),
        ndimage.uniform_filter(ndimage.gaussian_gradient_magnitude(image, 1.0), 9),
    ]
    plain = [ndimage.distance_transform_edt(image > EDGE_LEVEL), image]
    return np.stack([np.log(x + LOG_FLOOR) for x in logged] + plain)


def _area(x: torch.Tensor, grid: tuple[int, ...]) -> torch.Tensor:
    """Averaged onto the velocity grid, as the residual is (area averaging)."""
    return F.interpolate(x, size=grid, mode="area")


def _laplacian_energy_torch(field: torch.Tensor, window: int) -> torch.Tensor:
    """(1, C, *S) -> (1, 1, *S): the package's squared Laplacian (the border replicated, components summed), averaged
    over a ``window``-voxel box (the voxels outside counted as zeros, as the residual's boxes)."""
    energy = squared_laplacian(field)
    return box_sum(energy, window) / window ** (field.ndim - 2) if window > 1 else energy


def velocity_grid_features(warped, fixed, mean, log_var, displacement) -> torch.Tensor:
    """(1, len(FEATURES), *V): :func:`pair_features`' features computed with torch and averaged onto the velocity grid
    (what a product would compute within the maps' time): the edge distance becomes the fraction of the fixed image's
    foreground in a :data:`INSIDE_WINDOW`-voxel box, the gradient magnitude that of the image averaged over a
    3-voxel box (central differences)."""
    grid = tuple(mean.shape[2:])
    dims = fixed.ndim - 2
    with torch.inference_mode():
        residuals = [residual_variance(warped, fixed, grid, window=w) for w in (9, 3, 15)]
        laplacians = [_area(_laplacian_energy_torch(displacement, w), grid) for w in (5, 9, 15)]
        smooth = box_sum(fixed, 3) / 3**dims
        gradient = torch.stack(torch.gradient(smooth[:, 0], dim=tuple(range(1, dims + 1))), 1).norm(dim=1, keepdim=True)
        logged = [
            *residuals,
            _laplacian_energy_torch(mean, 1),
            *laplacians,
            log_var.exp().mean(1, keepdim=True),
            _area(displacement.norm(dim=1, keepdim=True), grid),
            _area(box_sum(gradient, 9) / 9**dims, grid),
        ]
        inside = _area(box_sum((fixed > EDGE_LEVEL).float(), INSIDE_WINDOW) / INSIDE_WINDOW**dims, grid)
        return torch.cat([(x + LOG_FLOOR).log() for x in logged] + [inside, _area(fixed, grid)], 1)


# name -> the features of one registered pair: (F, *S) numpy on the image grid, or (1, F, *V) torch on the velocity grid
FEATURE_SETS = {"scipy, image grid": pair_features, "torch, velocity grid": velocity_grid_features}


class ErrorModel:
    """``exp(features . coef + intercept)``: the predicted squared error (mm^2), of ``feature_set``'s features
    (:data:`FEATURE_SETS`), on the velocity grid."""

    def __init__(self, coef: np.ndarray, feature_set: str) -> None:
        self.coef, self.feature_set = np.asarray(coef, np.float64), feature_set

    def variance(self, warped, fixed, mean, log_var, displacement) -> torch.Tensor:
        """(1, 1, *V) the prediction on the velocity grid (the image-grid features' averaged onto it)."""
        features = FEATURE_SETS[self.feature_set](warped, fixed, mean, log_var, displacement)
        if isinstance(features, torch.Tensor):
            weights = torch.as_tensor(self.coef[:-1], dtype=features.dtype).view(1, -1, *[1] * (features.ndim - 2))
            return ((features * weights).sum(1, keepdim=True) + float(self.coef[-1])).exp()
        predicted = np.exp(np.tensordot(self.coef[:-1], features, axes=1) + self.coef[-1])
        return F.adaptive_avg_pool3d(torch.from_numpy(predicted)[None, None].float(), tuple(mean.shape[2:]))


class Captured:
    """What the command's path computed for the last pair (the experiment reads it by wrapping the functions
    ``registration.network`` calls: the refined displacement, the registered images, the posterior), and the spread
    to use in place of the residual (``model``: None, the shipped residual)."""

    def __init__(self) -> None:
        self.model: ErrorModel | None = None
        self.last: dict[str, torch.Tensor] = {}
        jacobian = registration_network.jacobian_determinant
        residual = registration_network.residual_variance
        maps = registration_network.posterior_maps

        def keep_displacement(displacement, *a, **k):
            self.last["displacement"] = displacement.detach().clone()
            return jacobian(displacement, *a, **k)

        def keep_images(warped, fixed, grid, *a, **k):
            self.last["warped"], self.last["fixed"] = warped.detach().clone(), fixed.detach().clone()
            return residual(warped, fixed, grid, *a, **k)

        def spread(network, mean, log_var, *a, residual=None, **k):
            if self.model is not None:
                residual = scaled(self.variance(mean, log_var), residual)
            self.last.update(mean=mean, log_var=log_var, residual=residual)
            return maps(network, mean, log_var, *a, residual=residual, **k)

        registration_network.jacobian_determinant = keep_displacement
        registration_network.residual_variance = keep_images
        registration_network.posterior_maps = spread

    def variance(self, mean, log_var) -> torch.Tensor:
        last = self.last
        return self.model.variance(last["warped"], last["fixed"], mean, log_var, last["displacement"])


def scaled(variance: torch.Tensor, residual: torch.Tensor) -> torch.Tensor:
    """``variance`` scaled to the mean of the pair's ``residual``."""
    return variance * (residual.mean() / variance.mean().clamp_min(torch.finfo(variance.dtype).tiny))


def ranking(std: np.ndarray, error: np.ndarray) -> float:
    """Mean over components of Spearman(std, |error|), both (3, N)."""
    return float(np.mean([spearman(std[k], np.abs(error[k])) for k in range(3)]))


def posterior_std(calibration: Calibration, mean, log_var, residual, size) -> torch.Tensor:
    """(3, *size) the calibrated velocity std upsampled to the image grid: the posterior's spread without sampling."""
    variance = calibration.std_scale**2 * (log_var.exp() + calibration.residual_weight * residual)
    variance = variance + (calibration.bias_fraction * mean).square()
    return F.interpolate(variance, size=size, mode="trilinear")[0].sqrt()


def fit_error_models(model, captured: Captured, index, templates: list[str], refinement) -> tuple[dict, dict, dict]:
    """Least squares of log |error|^2 on each feature set's features over the synthetic subjects of ``templates``:
    the models, their coefficients by feature name, and each set's median seconds per pair."""
    rows: dict[str, list] = {name: [] for name in FEATURE_SETS}
    seconds: dict[str, list] = {name: [] for name in FEATURE_SETS}
    targets = []
    for n, template in enumerate(templates):
        case = subject_case(template, index.images[template], FIT_SEED + n, VOXELS_PER_CASE, model.divisor)
        registered, last = registered_case(model, case, 2, refinement), captured.last
        grid = case.fixed.grid
        size = tuple(last["fixed"].shape[2:])
        for name, features_of in FEATURE_SETS.items():
            start = time.perf_counter()
            features = features_of(last["warped"], last["fixed"], last["mean"], last["log_var"], last["displacement"])
            seconds[name].append(time.perf_counter() - start)
            if isinstance(features, torch.Tensor):  # velocity grid: read at the voxels as the posterior is upsampled
                features = F.interpolate(features, size=size, mode="trilinear")[0].numpy()
            rows[name].append(
                np.stack(
                    [grid.to_fixed(f[..., None].astype(np.float32))[..., 0].reshape(-1)[case.voxels] for f in features],
                    1,
                )
            )
        warp = registered.warp.reshape(-1, 3)[case.voxels].astype(np.float64)
        truth = case.subject.true_warp.reshape(-1, 3)[case.voxels].astype(np.float64)
        error = np.linalg.solve(registered.affine[:3, :3], (warp - truth).T).T
        targets.append(np.log((error**2).sum(1) + SQUARED_ERROR_FLOOR))
        print(f"fit case {n + 1}/{len(templates)}: {template}", flush=True)
    models, coefficients = {}, {}
    for name in FEATURE_SETS:
        design = np.concatenate(rows[name])
        coef, *_ = np.linalg.lstsq(np.c_[design, np.ones(len(design))], np.concatenate(targets), rcond=None)
        models[name] = ErrorModel(coef, name)
        coefficients[name] = dict(zip([*FEATURES, "intercept"], coef.round(4).tolist()))
    return models, coefficients, {name: float(np.median(t)) for name, t in seconds.items()}


def subject_scores(model, captured: Captured, index, templates, refinement) -> tuple[list[float], list[float], list]:
    """The subject probe's cases (the calibration's seeds): the sampled std's and the posterior std's ranking, and
    each case's sampled (std, error, |deformable displacement|)."""
    sampled, exact, triples = [], [], []
    for n, template in enumerate(templates):
        case = subject_case(template, index.images[template], SUBJECT_SEED + n, VOXELS_PER_CASE, model.divisor)
        std, error, norm = subject_errors(model, case, model.calibration, POSTERIOR_SAMPLES, refinement)
        triples.append((std, error, norm))
        last = captured.last
        size = tuple(last["displacement"].shape[2:])
        posterior = posterior_std(model.calibration, last["mean"], last["log_var"], last["residual"], size).numpy()
        grid = case.fixed.grid
        posterior = np.stack([grid.to_fixed(p[..., None])[..., 0].reshape(-1)[case.voxels] for p in posterior])
        sampled.append(ranking(std, error))
        exact.append(ranking(posterior, error))
    return sampled, exact, triples


def cross_fitted_coverage(population: list, subject: list) -> dict[str, dict[str, float]]:
    """Coverage at 68% and 95% of each probe's cases, each half scored with the calibration refitted on the other
    half of both probes (``fit_calibration`` on the samples drawn at the shipped calibration, each probe matched on
    its own, as the refit's first pass: no re-sampling). ``population``, ``subject``: each case's (std, error, norm)."""
    halves = [(range(0, len(c) // 2), range(len(c) // 2, len(c))) for c in (population, subject)]
    hits: dict[str, dict[float, list]] = {"population": {0.68: [], 0.95: []}, "subject": {0.68: [], 0.95: []}}
    for fold in range(2):
        parts = [[], [], [], []]
        for group, (cases, split) in enumerate(zip((population, subject), halves)):
            for i in split[1 - fold]:
                std, error, norm = cases[i]
                for part, array in zip(parts, (std, error, norm, np.full(std.shape, group))):
                    part.append(array.reshape(-1))
        fitted = fit_calibration(*[np.concatenate(p) for p in parts[:3]], groups=np.concatenate(parts[3]))
        for name, cases, split in zip(hits, (population, subject), halves):
            for i in split[fold]:
                std, error, norm = cases[i]
                widened = np.sqrt((fitted.std_scale * std) ** 2 + (fitted.bias_fraction * norm) ** 2)
                for level in hits[name]:
                    inside = np.abs(error) <= interval_z(level, fitted.interval_dof) * widened
                    hits[name][level].append(inside.reshape(-1))
    return {
        name: {f"{round(level * 100)}%": float(np.concatenate(v).mean()) for level, v in levels.items()}
        for name, levels in hits.items()
    }


def main(argv: Sequence[str] | None = None) -> int:
    ap = study_parser(__doc__, RESULTS)
    ap.add_argument("--fit-templates", type=int, default=8, help="training templates the error model is fitted on")
    args = ap.parse_args(argv)
    started = study_start(args)
    if started is None:
        return 0
    setup = started.setup
    index = started.index
    model = dataclasses.replace(
        load_model(args.bundle_root, setup.model_file, calibrate=True, quality=False), quality=None
    )
    calibration = model.calibration
    training = [i for i in index.ids if i not in setup.val_ids]
    probe_templates = training[:SUBJECT_PROBE_TEMPLATES]
    fit_templates = training[SUBJECT_PROBE_TEMPLATES : SUBJECT_PROBE_TEMPLATES + args.fit_templates]
    captured = Captured()
    error_models, coefficients, feature_seconds = fit_error_models(
        model, captured, index, fit_templates, setup.refinement
    )
    for name, coef in coefficients.items():
        print(f"{name} ({feature_seconds[name]:.2f} s a pair): " + ", ".join(f"{k} {v:+.3f}" for k, v in coef.items()))
    spreads = {"residual (shipped)": None, **{f"error model, {name} features": m for name, m in error_models.items()}}
    rows: dict[str, dict] = {name: {} for name in spreads}
    subject_triples: dict[str, list] = {}
    for name, spread in spreads.items():
        captured.model = spread
        sampled, exact, triples = subject_scores(model, captured, index, probe_templates, setup.refinement)
        rows[name].update(subject_sampled=sampled, subject_posterior=exact)
        subject_triples[name] = triples
        print(f"{name}: subject probe {np.mean(sampled):.3f} sampled, {np.mean(exact):.3f} posterior", flush=True)
    # the population probe: the validation subjects' cases, each pair's registered images kept
    pairs = []

    def keep_pair(warped, fixed, grid):
        pairs.append((warped.clone(), fixed.clone()))
        return residual_variance(warped, fixed, grid)

    population_probe.residual_variance = keep_pair
    probes, cases = population_probe_cases(args, started)
    shipped = [c["residual"] for c in cases]
    for name, spread in spreads.items():
        sampled, exact, triples = [], [], []
        for case, residual, (warped, fixed) in zip(cases, shipped, pairs):
            if spread is not None:
                with torch.inference_mode():
                    displacement = setup.network.velocity_to_displacement(case["mean"], case["size"])
                residual = scaled(spread.variance(warped, fixed, case["mean"], case["log_var"], displacement), residual)
            case["residual"] = residual
            std, error, norm = sampled_case_errors(setup.network, case, calibration, POSTERIOR_SAMPLES)
            triples.append((std, error, norm))
            posterior = posterior_std(calibration, case["mean"], case["log_var"], residual, case["size"])
            sampled.append(ranking(std, error))
            exact.append(ranking(posterior.flatten(1)[:, case["voxels"]].numpy(), error))
        rows[name].update(population_sampled=sampled, population_posterior=exact)
        rows[name]["coverage_refitted"] = cross_fitted_coverage(triples, subject_triples[name])
        print(f"{name}: coverage, refitted on the other half: {rows[name]['coverage_refitted']}", flush=True)
        print(f"{name}: population probe {np.mean(sampled):.3f} sampled, {np.mean(exact):.3f} posterior", flush=True)
    # the label entropy on the validation subjects' real pairs (subject -> atlas), as the calibration benchmark scores it
    preprocessing = setup.evaluate.get_parsed_content("preprocessing")
    refinement = setup.evaluate.get_parsed_content("refinement")
    for name, spread in spreads.items():

        def posterior_for(network, moving, fixed, refinement=None, spread=spread):
            output = register_pair(network, moving, fixed, refinement)
            with torch.inference_mode():
                residual = residual_variance(output.warped, fixed, output.velocity_mean.shape[2:])
                if spread is not None:
                    predicted = spread.variance(
                        output.warped, fixed, output.velocity_mean, output.velocity_log_var, output.displacement
                    )
                    residual = scaled(predicted, residual)
            return PairPosterior(output.velocity_mean, output.velocity_log_var, residual)

        uncertainty_calibration.posterior_for = posterior_for
        aurocs = []
        for n, item in enumerate(Dataset(labelled_pairs(index, setup.val_ids), transform=preprocessing)):
            pair = {k: plain_tensor(v)[None] if isinstance(v, torch.Tensor) else v for k, v in item.items()}
            labels = label_case(setup.network, pair, calibration, POSTERIOR_SAMPLES, SEED_STRIDE * n + 2, refinement)
            aurocs.append(labels["auroc"])
        rows[name]["label_auroc"] = aurocs
        print(f"{name}: label AUROC {np.mean(aurocs):.3f}", flush=True)
    lines = [
        "| spread (shipped calibration, nothing refitted) | subject probe: 16 samples | subject probe: posterior std "
        "| population probe: 16 samples | population probe: posterior std | label-entropy AUROC "
        "| coverage 68% / 95% refitted on the other half: population | subject probe |",
        "|---|---|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {name} | {np.mean(r['subject_sampled']):.3f} | {np.mean(r['subject_posterior']):.3f} "
        f"| {np.mean(r['population_sampled']):.3f} | {np.mean(r['population_posterior']):.3f} "
        f"| {np.mean(r['label_auroc']):.3f} "
        f"| {r['coverage_refitted']['population']['68%']:.3f} / {r['coverage_refitted']['population']['95%']:.3f} "
        f"| {r['coverage_refitted']['subject']['68%']:.3f} / {r['coverage_refitted']['subject']['95%']:.3f} |"
        for name, r in rows.items()
    ]
    result = {
        "calibration": calibration._asdict(),
        "samples": POSTERIOR_SAMPLES,
        "fit_templates": fit_templates,
        "fit_seeds": [FIT_SEED + n for n in range(len(fit_templates))],
        "probe_templates": probe_templates,
        "subjects": list(setup.val_ids),
        "coefficients": coefficients,
        "feature_seconds_per_pair": feature_seconds,
        "rows": rows,
    }
    return finish_study(args, "error_model", started, result, lines)


if __name__ == "__main__":
    sys.exit(main())

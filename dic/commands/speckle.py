"""``specula speckle``: speckle quality of a reference image (MIG, SSSIG) and a subset-size suggestion."""
from __future__ import annotations

from pathlib import Path

import click

from ._region import parse_region, region_options


@click.command(name="speckle", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("reference", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--target", default=0.01, show_default=True, type=click.FloatRange(min=0, min_open=True),
              help="Target displacement standard deviation, px.")
@click.option("--subset", default=21, show_default=True, type=int,
              help="Subset side in px (odd) for the MIG / SSSIG statistics.")
@click.option("--step", default=10, show_default=True, type=click.IntRange(min=1), help="Grid spacing of the points, px.")
@click.option("--order", default="1", show_default=True, type=click.Choice(["1", "2"]),
              help="Shape function of the suggestion: 1 (affine) or 2 (quadratic, ~1.9x the std).")
@click.option("--coverage", default=0.95, show_default=True, type=click.FloatRange(min=0, max=1, min_open=True),
              help="Share of the points that must meet the target.")
@click.option("--noise-sigma", default=None, type=click.FloatRange(min=0, min_open=True, max=1e6),
              help="Image noise std in grey levels, at most 1e6 (default: from --second, else estimated from REFERENCE).")
@click.option("--second", default=None, type=click.Path(dir_okay=False, path_type=Path),
              help="A second image of the unmoved specimen: the noise is measured from the difference.")
@region_options
@click.option("--device", default=None, help="Warp device: cpu, cuda, cuda:N (default: CUDA when present).")
def speckle(reference, target, subset, step, order, coverage, noise_sigma, second, roi, roi_polygon, mask, exclude,
            device):
    """Speckle quality of REFERENCE: mean intensity gradient (MIG), SSSIG and the smallest subset for --target.

    The predicted displacement std of a point is sqrt(2 noise^2 diag H^-1) with the IC-GN Hessian H
    of its subset (docs/dic2d.md, "Uncertainty" and "Speckle quality"). A region of interest (--roi,
    --roi-polygon or --mask, less any --exclude shapes) restricts the points to the specimen: a
    featureless background, black borders or a hole would otherwise push the suggestion up.
    """
    import numpy as np

    from dic.io import read_image
    from dic.quality import estimate_noise, speckle_quality, suggest_subset

    if subset < 5 or subset % 2 == 0:
        raise click.BadParameter(f"the subset must be an odd number of px >= 5, got {subset}", param_hint="--subset")
    if second is not None and noise_sigma is not None:
        raise click.UsageError("give either --noise-sigma or --second, not both")
    roi_given = parse_region(roi, roi_polygon, mask, exclude)
    try:
        ref = read_image(reference)
        region = None
        if roi_given is not None:
            from dic.correlation.points import region as check_region

            region = check_region(roi_given, ref.shape)
        if noise_sigma is not None:
            noise, how = noise_sigma, "given"
        elif second is not None:
            noise, how = estimate_noise(ref, read_image(second)), f"measured from the difference with {second.name}"
        else:
            noise = estimate_noise(ref)
            how = ("estimated from the flattest 10 % of the image: an upper bound on sharp speckle; "
                   "--second or --noise-sigma give a tighter one")
        if not noise > 0:
            raise ValueError("the measured noise is 0 (identical images?); give --noise-sigma")
        q = speckle_quality(ref, subset, step=step, roi=region, noise_sigma=noise, device=device)
        s = suggest_subset(ref, target, noise, order=int(order), coverage=coverage, step=step, roi=region,
                           device=device)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    h, w = ref.shape
    st = q.summary()
    sig = np.max(q.sigma_1st, axis=1)
    sig = sig[np.isfinite(sig)]
    pct = round(100 * coverage)
    click.echo(f"{reference.name}: {w}x{h} px, noise sigma {noise:.3g} grey levels ({how})")
    click.echo(f"image MIG: {st['image_mig']:.4g} grey levels/px")
    click.echo(f"region: {region.describe() if region is not None else 'whole image (no --roi/--exclude)'}")
    click.echo(f"subset {subset} px, {q.points.shape[0]} points (step {step} px):")
    click.echo(f"  MIG   median {st['mig_median']:.4g}, 5th percentile {st['mig_p5']:.4g} grey levels/px")
    click.echo(f"  SSSIG min(x, y) median {st['sssig_median']:.4g}, 5th percentile {st['sssig_p5']:.4g} "
               "grey levels^2/px^2")
    if sig.size:
        click.echo(f"  predicted std (1st order) median {np.median(sig):.3g} px, "
                   f"{pct}th percentile {np.quantile(sig, coverage):.3g} px")
    tried = ", ".join(f"{k}: {v:.3g}" for k, v in s.tried.items())
    if s.subset is not None:
        click.echo(f"suggested subset: {s.subset} px (order {order}: {pct} % of points at or below {target:g} px)")
    else:
        click.echo(f"no subset up to {max(s.tried) if s.tried else subset} px meets {target:g} px at {pct} % of points "
                   f"(order {order}); improve the speckle or the noise, or accept a larger target")
    click.echo(f"  predicted std at the {pct}th percentile per subset (px): {tried}")

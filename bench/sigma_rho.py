"""The u-v error correlation of subsets on speckle: |rho_uv| (dic.quality.SigmaBasis.rho_uv) over the POIs.

``python -m bench.sigma_rho`` prints, per shape-function order and subset size, the median, 95th
percentile and maximum of |rho| = |(H^-1)_uv| / sqrt((H^-1)_uu (H^-1)_vv) over 1024 POIs (step 9 px)
of a 320 x 320 speckle image of dic.synth.speckle_pair (radius 2 px, blur 0.7, seed 11). The figures
are in docs/dic2d.md ("The u-v covariance"). CPU, a few seconds.
"""
import numpy as np

from dic.quality import sigma_basis
from dic.synth import speckle_pair
from kernels.icgn import prepare_reference, prepare_subsets


def main() -> None:
    ref, _ = speckle_pair((320, 320), (0.3, 0.0), radius=2.0, blur=0.7, seed=11, device="cpu")
    ys, xs = np.mgrid[20:300:9, 20:300:9]
    pts = np.column_stack([xs.ravel(), ys.ravel()]).astype(float)
    prep = prepare_reference(ref, device="cpu")
    for order in (1, 2):
        for subset in (11, 21, 31):
            b = sigma_basis(prepare_subsets(prep, pts, subset=subset, order=order))
            r = np.abs(b.rho_uv[np.isfinite(b.rho_uv)])
            print(f"order {order} subset {subset}: {r.size} POIs, |rho| median {np.median(r):.3f}, "
                  f"p95 {np.percentile(r, 95):.3f}, max {r.max():.3f}")


if __name__ == "__main__":
    main()

"""Independent full-image scores of fixtures/scores/render.png against gt.png (scikit-image).

The render is an `xscale train --preset tiny` render of view 0000 of `xscale synth --preset small
--seed 1`, trained on the scene mesh with a 30 m hole cut in its middle (`--mesh holed.ply`):
where the mesh misses, the render is white (the background) while the photo shows terrain. The
full-image scores must see that error; `tests/eval_protocol.rs`
(full_image_scores_match_scikit_image) checks xscale's against the numbers this script writes to
fixtures/scores/expected.json: PSNR to 0.01 dB, SSIM to 1e-4, and the mean ꟻLIP error to 1e-6
against NVIDIA's own Python package (flip-evaluator; LDR, 67 pixels per degree as xscale's nv-flip
default, the error map averaged in float64).

Run: python reference/scores_case.py            (needs numpy, scikit-image, flip-evaluator; rewrites
                                                 expected.json)
     python reference/scores_case.py --check    (recomputes and compares with the committed file)
Last written with scikit-image 0.26.0, numpy 2.4.6, flip-evaluator 1.7 (PSNR and SSIM: the same
numbers to the last digit as the first version of the file, which had no ꟻLIP).
"""
import json
import sys
from pathlib import Path

import flip_evaluator
import numpy as np
import skimage
from skimage.io import imread
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

CASE = Path(__file__).resolve().parent.parent / "fixtures" / "scores"


def scores() -> dict:
    render = imread(CASE / "render.png")[..., :3]
    gt = imread(CASE / "gt.png")[..., :3]
    r, g = render.astype(np.float64) / 255.0, gt.astype(np.float64) / 255.0
    return {
        # The untouched photo against the render, every pixel: the honest full-image PSNR.
        "psnr": float(peak_signal_noise_ratio(gt, render, data_range=255)),
        "ssim": float(structural_similarity(
            g, r, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
            data_range=1.0, channel_axis=-1)),
        # The official protocol paints the photo white wherever the render missed (white): what
        # the full-image PSNR used to report, for comparison.
        "psnr_gt_painted_white": float(peak_signal_noise_ratio(
            np.where((render == 255).all(-1, keepdims=True), 255, gt), render, data_range=255)),
        # NVIDIA's LDR ꟻLIP of the render against the untouched photo, mean of the error map.
        # flip-evaluator's own default derives 67.02 pixels per degree from its viewing
        # conditions; xscale uses nv-flip's DEFAULT_PIXELS_PER_DEGREE, 67.
        "flip": float(flip_evaluator.evaluate(
            g.astype(np.float32), r.astype(np.float32), "LDR", applyMagma=False,
            computeMeanError=False, parameters={"ppd": 67.0})[0].astype(np.float64).mean()),
    }


def main() -> int:
    out = scores()
    if "--check" in sys.argv[1:]:
        committed = json.loads((CASE / "expected.json").read_text())
        bad = {k: (committed.get(k), v) for k, v in out.items() if committed.get(k) != v}
        print(f"scikit-image {skimage.__version__}: {out}")
        if bad:
            print(f"differs from fixtures/scores/expected.json: {bad}")
            return 1
        print("fixtures/scores/expected.json: the same numbers")
        return 0
    (CASE / "expected.json").write_text(json.dumps(out, indent=2))
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())

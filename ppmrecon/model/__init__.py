"""The consistent learned post-reconstruction (Choi & Moon 2021, paper 002 Sec. 4.2-4.3).

    combine.py     Eq. 6: the consistent multi-buffer combiner (exact convexity bound)
    guard.py       the consistent firefly guard: outlier inputs -> 3x3 median, output band
    features.py    network inputs from a buffer file (27 channels + optional extras)
    kpn.py         the kernel-predicting network and its presets (ppmrecon/data/models/)
    checkpoint.py  save/load models (weights + architecture + feature settings)
    infer.py       tiled, threaded inference: buffer file -> denoised RGB
    cli.py         ppmrecon-denoise
"""

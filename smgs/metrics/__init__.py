"""Metrics, computed once, in one place.

- ``image``: 8-bit quantisation like 3DGS's PNG round trip, PSNR, SSIM, LPIPS, FLIP per image
  (``evaluate_images``).
- ``ssim``: SSIM as 3DGS computes it (differentiable; the training loss uses it too).
- ``lpips`` / ``lpips_weights``: LPIPS in PyTorch from local weights; one-command weight setup.
- ``flip``: ꟻLIP through ``flip-evaluator`` as a raw error map.
- ``timing``: render FPS, peak memory, train-seconds accounting.
- ``consistency``: RAFT-free view consistency (Table 4 of the Softmax-GS paper).
- ``result``: ``Missing(reason)``, what a metric that could not be computed reports.
"""

"""Weight-free perception back ends: graph segmentation with region merging, and colour/texture descriptors.

The segmenter (`segmenter.py`) over-segments each image at a fixed working resolution
(Felzenszwalb graph segmentation or SLIC superpixels from scikit-image) and then merges adjacent
regions hierarchically on a region adjacency graph whose edge weights combine the regions' Lab
colour, their local contrast and the colour step along their shared border. The merging works on
region statistics with vectorized numpy; only the over-segmentation itself runs per image.

The describers (`describers.py`) pool one per-pixel feature map (`pixel_features.py`: soft hue
histogram of brightness-normalized chromaticity plus an achromatic bin, and a soft histogram of
brightness-relative gradient magnitude) over masks with one batched einsum (segments) or with
generalized-mean pooling over a spatial pyramid (whole images).
"""

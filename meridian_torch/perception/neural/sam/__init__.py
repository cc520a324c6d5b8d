"""Segment Anything (SAM): our implementation of the official architecture (loads the official
`sam_vit_{b,l,h}_*.pth` files strictly), the automatic mask generator and the `sam` segmenter.

`model.py` builds and loads models and holds the ONNX export views; `automatic.py` generates
masks and implements the Segmenter protocol.
"""

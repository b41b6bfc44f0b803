"""Pretrained base models shipped with FreiPose (weights and their model card data)."""

"""Deployment artefacts (ONNX graphs) built with :mod:`torchcontact.export`; see ``__main__``."""

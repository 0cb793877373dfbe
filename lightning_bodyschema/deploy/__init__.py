"""Deployment: the prepared diffusion adapter as one AOTInductor package a C++ controller can call.

``AdapterModule`` (the tensor-only adapter), ``export_package`` (torch.export + AOTInductor, with metadata) and
``load_exported`` (the package as ``(q_ref, faults) -> AdaptationResult``); ``STATUS_CODES`` the package's statuses.
"""
from .module import STATUS_CODES, AdapterModule
from .package import ExportedAdapter, export_package, load_exported

__all__ = ["STATUS_CODES", "AdapterModule", "ExportedAdapter", "export_package", "load_exported"]

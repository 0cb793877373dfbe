"""Deployment: a schema's prepared adapter (diffusion or structured) as one AOTInductor package a C++ controller can
call.

``AdapterModule`` / ``StructuredAdapterModule`` (the tensor-only adapters), ``export_package`` (torch.export +
AOTInductor, with metadata) and ``load_exported`` (the package as ``(q_ref, faults) -> AdaptationResult``, checked
against a pinned SHA-256 before it is loaded); ``STATUS_CODES`` the package's statuses (``status.Status`` codes).
"""
from ..status import STATUS_CODES
from .module import AdapterModule
from .package import ExportedAdapter, check_digest, export_package, file_sha256, load_exported
from .structured import StructuredAdapterModule

__all__ = ["STATUS_CODES", "AdapterModule", "StructuredAdapterModule", "ExportedAdapter", "check_digest",
           "export_package", "file_sha256", "load_exported"]

"""The REST API under ``/v1``: rigs (upload, fit, describe, download, delete) and performer
calibrations.
"""

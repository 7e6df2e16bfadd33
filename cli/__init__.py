"""sefa's command line (installed as `sefa_cli`; this folder is its source). Import it as
`sefa_cli`: under the folder's own name the modules would load a second time, beside the
installed ones."""

if __name__ != "sefa_cli":
    import warnings

    warnings.warn(f"'{__name__}' is the folder's name; import sefa_cli", DeprecationWarning, stacklevel=2)

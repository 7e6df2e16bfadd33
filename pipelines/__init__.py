"""The workspace: stage graph, cached runner, presets (installed as `sefa_pipelines`; this folder
is its source). Import it as `sefa_pipelines`: under the folder's own name the modules would load
a second time, beside the installed ones."""

if __name__ != "sefa_pipelines":
    import warnings

    warnings.warn(f"'{__name__}' is the folder's name; import sefa_pipelines", DeprecationWarning,
                  stacklevel=2)

"""Command-line interface (``magail-sumo``)."""

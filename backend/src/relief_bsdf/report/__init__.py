"""Figures and reports (matplotlib, written atomically): nothing here computes physics.

    plots       table_figure / compare_figure / plot_in_plane / plot_polar_map / save_figure
                (`relief plot`)
    fit_report  fit_plots / write_fit_report / in_plane_figure / residual_map_figure / residual_image
                (`relief fit`; the residual map is shared with the diagnosis report)
    html        the house style of the HTML reports: self-contained pages, formatted numbers, intervals
Import the sub-modules directly: they load matplotlib (Agg backend) on import.
"""

__all__ = ["plots", "fit_report", "html"]

"""Files and settings: the TOML config and what it builds, the interchange CSV files,
importers of outside data sets, `keo estimate` over files and the analysis report."""

"""The paper's warm-start analysis (section V): runs, metrics, figures and report."""

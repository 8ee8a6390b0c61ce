"""Reports: error statistics, JSON / Markdown files and plots for calibrations, loops and fleets."""

"""Analysis of finished runs: curves and tables (plot), interval estimates and exact tests (stats), the claims table,
evaluating and exporting a trained policy. It reads run folders and CSVs; nothing else imports it."""

"""Reading finished runs, apart from the training engine: the quality-against-time report (``report``), wavelet
diagnostics figures (``diagnostics``), the shared figure helper (``figures``) and camera paths for videos
(``camera_path``). Nothing in ``engine`` imports this package."""

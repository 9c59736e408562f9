"""The persistent building map: its data model (``model``), fusion of a new observation into it (``refine``:
Kalman-style layer depths, IoU matching of elements, per-pixel window votes, roofs from aerial scans), the campaign
update over whole cities (``update``: grouped buildings on serial or dask workers), the use case "update a map file"
(``apply``) and the SQLite store with history, transactions and locking (``store``).
"""

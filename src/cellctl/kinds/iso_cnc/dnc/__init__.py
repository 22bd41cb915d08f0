"""``cellctl dnc``: the DNC server for the shop's iso-cnc controls (docs/dnc.md).

- :mod:`.store`: the shop directory (programs, received and sent copies, the log);
- :mod:`.request`: the remote-request convention (``O9999 (LOAD O1234)``);
- :mod:`.config`: ``dnc.toml`` (or a cell's iso-cnc machines);
- :mod:`.diff`: a received program against what was sent;
- :mod:`.server`: many machines from one process, each on its own link;
- :mod:`.access` / :mod:`.cli`: its control API and its commands; :mod:`.hand_cli`: how a
  hand command reaches a machine (through the running server, or on a link opened here).
"""

"""Where data comes in: one module per way, samples out.

- :mod:`.samples`: the typed :class:`~app.sources.samples.Sample` every source yields;
- :mod:`.sensorfusion` (the Sensor Fusion app's line format) and
  :mod:`.sensorfusion_tcp` (its TCP receiver);
- :mod:`.sensorlogger` (Sensor Logger's HTTP push) and :mod:`.phyphox` (phyphox's
  push and remote access);
- :mod:`.ordering`: time ordering of samples from any source, on the phone's clock;
- :mod:`.readers`: recorded logs (the app's format, CSV, npz);
- :mod:`.simulate` (the demo phone) and :mod:`.runners` (demo and replay at real time).

Nothing here imports the live core, the toolkit or the server.
"""

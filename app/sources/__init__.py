"""Where data comes in: one module per way, samples out.

- :mod:`.samples`: the typed :class:`~app.sources.samples.Sample` every source yields;
- :mod:`.sensorfusion` (the Sensor Fusion app's line format; its TCP receiver, the
  network edge, is the server's :mod:`app.server.tcp_phone`);
- :mod:`.sensorlogger` (Sensor Logger's HTTP push) and :mod:`.phyphox` (phyphox's
  push and remote access);
- :mod:`.ordering`: time ordering of samples from any source, on the phone's clock;
- :mod:`.readers`: recorded logs (the app's format, CSV, npz);
- :mod:`.simulate` (the demo phone) and :mod:`.pacing` (a log's playhead at real time);
- :mod:`.slot`: the one phone slot every receiver shares.

Nothing here imports the live core, the toolkit or the server, nor drives the engine: a
source turns a wire format into samples; the server's receivers and background tasks
(:mod:`app.server.tcp_phone`, :mod:`app.server.phones`, :mod:`app.server.background`)
hand them on.
"""

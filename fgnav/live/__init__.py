"""The live link: MAVLink 2 to and from a flight controller (``fgnav live``), and a stand-in
autopilot that sends a logged or simulated flight as those messages (``fgnav replay``).

Modules: :mod:`~fgnav.live.convert` (frames and units at the edge, the only place they change),
:mod:`~fgnav.live.inbound` (messages -> events on the boot clock, counted),
:mod:`~fgnav.live.link` (UDP socket read on a thread), :mod:`~fgnav.live.estimators` (what the
link drives), :mod:`~fgnav.live.session` (``fgnav live``), :mod:`~fgnav.live.replay`
(``fgnav replay``). Needs ``pymavlink`` (``pip install -e '.[live]'``).
"""

"""Opens a transport (callback subscriber, token, publisher) and a recorder, then exits without closing them.

    python tests/comms/exit_without_close.py ENDPOINT MCAP_PATH
"""

import sys

from flightdata.recorder import Recorder
from comms.transport import Transport, TransportConfig
from shared_msgs import Health, keys

bus = Transport.open(TransportConfig.rendezvous(sys.argv[1]), "leaky")
bus.subscribe("skycap/**", lambda rx: None)
bus.declare_alive(keys.alive_key("f", "leaky"))
rec = Recorder(sys.argv[2], node_id="leaky")
data = bus.publish(keys.node_key("f", "leaky", keys.HEALTH), Health(header=Health.make_header("leaky"), role="tool", state="x"))
rec.record("health", data)
print("exiting without close", flush=True)

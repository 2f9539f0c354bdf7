"""The daemon: many loops, each with the PIDAT block's state machine, their sessions, records and devices.

Its rooms, each a module:

==================  =================================================================================
``manager``         :class:`LoopManager`: the state machine of every loop (TUNE, TBRK, apply, restores,
                    the device's handshake), its life cycle (start with crash recovery, shutdown that
                    hands every loop back first) and what the field reports
``loop``            :class:`Loop`: one loop as the manager holds it, its running :class:`Session`, its
                    status record
``status``          :class:`LoopStatus`: the typed status REST, the event streams and OPC UA share
``settings``        :class:`Settings` of a session (a TUNE completed with the loop's defaults) and the
                    :class:`~autotuner.service.link_session.SessionPlan` they make
``refused``         :class:`Refused`: a request the state does not allow, with its machine code
``recorder``        the history's thread: every write in order, bounded waits
``events``          a loop's subscribers and trend
``restore``         a loop not handed back yet (:class:`Pending`) and one try at it
``field``           everything that touches a device: the :class:`Field` interface and
                    :class:`LocalField` (this event loop)
``sampler``         the field in sampler processes of its own (:class:`SamplerField`)
``watch``           a loop's monitor and handshake
``reach``           how a loop is reached (its link or simulated PLC) and the fresh check before a TUNE
``health``          a loop's online health: its readings over the window, the job a worker assesses, the
                    summary and detail REST, the streams and OPC UA show
==================  =================================================================================
"""

from autotuner.service.daemon.field import Field, LocalField, Reach
from autotuner.service.daemon.loop import Loop, Session
from autotuner.service.daemon.manager import PLC_USER, LoopManager
from autotuner.service.daemon.reach import connector, fresh_check, simulated_plc
from autotuner.service.daemon.refused import Refused
from autotuner.service.daemon.restore import Pending, found
from autotuner.service.daemon.settings import Settings, plan_of, relay_config, settings_of
from autotuner.service.daemon.status import LoopStatus

__all__ = ["PLC_USER", "Field", "LocalField", "Loop", "LoopManager", "LoopStatus", "Pending", "Reach", "Refused",
           "Session", "Settings", "connector", "found", "fresh_check", "plan_of", "relay_config", "settings_of",
           "simulated_plc"]

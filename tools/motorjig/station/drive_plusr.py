"""The Plus-R drive behind the jig's PC port as a station ``Drive``: today's ``Master`` calls.

``PlusRDrive(master, slave, jig_id)`` wraps the calls the Plus-R step kinds make
(GetSlaveInfo, ServoEnable, AlarmReset, GetAlarmType, MoveStop, EmergencyStop, the
jig's counters, ``plug.make_safe``) unchanged; the Plus-R phases still reach ``master``
and ``slave`` for the frames only this protocol has (parameters by number, the Ex move
frames, the jig's own sampler, ``station.sampling``).
"""

from motorjig.station.drive import Drive


class PlusRDrive(Drive):
    protocol = "plusr"
    emergency_words = "EmergencyStop, servo off"

    def __init__(self, master, slave, jig_id=1):
        self.master, self.slave, self.jig_id = master, slave, jig_id
        self.is_servo = False  # Ezi-SERVO: its alarm reset is a servo off/on (set by the run's preflight)
        self.label = "slave %d" % slave

    def identify(self):
        info = self.master.get_slave_info(self.slave)
        return {"slave_type": info.type, "slave_name": info.version}

    def motor(self):
        return self.master.get_motor_info(self.slave).text

    def enable(self, on):
        self.master.servo_enable(self.slave, on)
        return {"servo_on": self.master.get_axis_status(self.slave).servo_on}

    def fault_reset(self):
        self.master.alarm_reset(self.slave, servo=self.is_servo)

    def fault(self):
        return self.master.get_alarm_type(self.slave).code

    def quick_stop(self):
        self.master.emergency_stop(self.slave)

    def halt(self):
        self.master.move_stop(self.slave)

    def bus_health(self):
        return self.master.read_counters(self.jig_id)

    def make_safe(self, emergency=False):
        from motorjig.station.plug import make_safe

        return make_safe(self.master, self.slave, emergency)

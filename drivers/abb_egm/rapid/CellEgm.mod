MODULE CellEgm
    !-------------------------------------------------------------------------------------------
    ! EGM joint guidance for the cellctl daemon (RobotWare 6.08+ / RobotWare 7, task T_ROB1).
    !
    ! Sequence per program start (cycle "once"):
    !   fine point -> EGMGetId -> EGMSetupUC (joint mode, communication timeout) -> EGMActJoint
    !   (speed / position deviation limits, filter, sample rate) -> EGMRunJoint (long condition
    !   time, so the session lasts until the daemon ends it) -> EGMReset.
    !
    ! The daemon writes the PERS data below through RWS before it starts the program, then streams
    ! joint references (EgmSensor, MSGTYPE_CORRECTION, planned.joints in degrees; with a track also
    ! planned.externalJoints in mm, see EGM_TRACK) every 4 ms to the
    ! UdpUc device EGM_DEVICE. It ends the session by writing egm_end := TRUE (or by setting the
    ! digital output DO_EGM_END). egm_status tells the daemon how the last session ended.
    !
    ! The controller simulator (drivers/abb_egm/sim/model.py) models exactly this program, and
    ! drivers/abb_egm/rapid_values.py names its variables and egm_status values for the client and
    ! the simulator: keep them in step with it.
    !-------------------------------------------------------------------------------------------

    ! --- written by the daemon through RWS (defaults suit a first test) ---
    ! TRUE ends the running session (EGMStop, hold position); main resets it to FALSE at start.
    PERS bool egm_end:=FALSE;
    ! No EgmSensor message for this long (s) raises 41822 "No data from the UdpUc device".
    PERS num egm_comm_timeout_s:=1;
    ! Position-correction gain 0..1 (k = gain x Default Proportional Position Gain); 0 = pure speed.
    PERS num egm_pos_corr_gain:=1;
    ! Largest allowed change of the joint speed reference (deg/s). ABB's default of 1 deg/s is
    ! far too small for guidance, so this is set high and the daemon limits its own references.
    PERS num egm_max_speed_dev_dps:=1000;
    ! Largest allowed deviation from the start fine point (deg).
    PERS num egm_max_pos_dev_deg:=1000;
    ! Convergence must hold this long (s) before EGMRunJoint returns by itself: effectively never.
    PERS num egm_cond_time_s:=1000000;
    ! Ramp-in time of the corrections (s).
    PERS num egm_ramp_in_s:=0.05;
    ! Low-pass filter bandwidth of the corrections (Hz).
    PERS num egm_lp_filter_hz:=20;
    ! EGM cycle (ms); a multiple of 4.
    PERS num egm_sample_rate_ms:=4;

    ! --- written by this module, read by the daemon ---
    ! 0 idle, 1 session running, 2 ended on request (egm_end / DO_EGM_END or convergence),
    ! -41822 communication timeout, -1 any other EGM error (details in the event log).
    PERS num egm_status:=0;

    ! UdpUc device (Configuration > Communication > UDP Unicast Device) and the External Motion
    ! Interface Data instance (Configuration > Motion) this module uses.
    CONST string EGM_DEVICE:="EGM_DAEMON";
    CONST string EGM_MOTION_DATA:="default";
    ! Convergence band per joint (deg). Narrow, and with the long condition time above the
    ! session does not end on convergence while the daemon holds the robot still.
    CONST egm_minmax EGM_CONV:=[-0.1,0.1];
    ! The linear track ([robot.track] in cell.toml): TRUE when the robot rides on one. The track is
    ! an additional axis of this task's motion group (docs/robot-setup.md, "Linear track"); EGM then
    ! guides it with the arm as the 7th axis: its reference and feedback travel in externalJoints
    ! (mm), and \MaxPosDeviation applies to it in mm. Convergence band for it (mm):
    CONST bool EGM_TRACK:=FALSE;
    CONST egm_minmax EGM_CONV_TRACK:=[-0.1,0.1];

    VAR egmident egm_id;
    VAR intnum end_var_int;
    VAR intnum end_sig_int;
    VAR jointtarget jt_start;

    PROC main()
        egm_end:=FALSE;
        egm_status:=1;
        ! EGM must start from a fine point, and the first move after a restart must be an ordinary
        ! RAPID move: stand still where the robot is.
        jt_start:=CJointT();
        MoveAbsJ jt_start,v10,fine,tool0;
        ! A previous run that stopped half way may still hold an identity.
        EGMReset egm_id;
        EGMGetId egm_id;
        EGMSetupUC ROB_1,egm_id,EGM_MOTION_DATA,EGM_DEVICE\Joint\CommTimeout:=egm_comm_timeout_s;
        IF EGM_TRACK THEN
            EGMActJoint egm_id
                \J1:=EGM_CONV\J2:=EGM_CONV\J3:=EGM_CONV\J4:=EGM_CONV\J5:=EGM_CONV\J6:=EGM_CONV
                \J7:=EGM_CONV_TRACK
                \LpFilter:=egm_lp_filter_hz
                \SampleRate:=egm_sample_rate_ms
                \MaxPosDeviation:=egm_max_pos_dev_deg
                \MaxSpeedDeviation:=egm_max_speed_dev_dps;
        ELSE
            EGMActJoint egm_id
                \J1:=EGM_CONV\J2:=EGM_CONV\J3:=EGM_CONV\J4:=EGM_CONV\J5:=EGM_CONV\J6:=EGM_CONV
                \LpFilter:=egm_lp_filter_hz
                \SampleRate:=egm_sample_rate_ms
                \MaxPosDeviation:=egm_max_pos_dev_deg
                \MaxSpeedDeviation:=egm_max_speed_dev_dps;
        ENDIF
        ! The end request reaches EGMRunJoint through a trap, because EGMRunJoint blocks this task.
        IDelete end_var_int;
        CONNECT end_var_int WITH EndEgmTrap;
        IPers egm_end,end_var_int;
        IDelete end_sig_int;
        CONNECT end_sig_int WITH EndEgmTrap;
        ISignalDO DO_EGM_END,1,end_sig_int;
        ! Without \NoWaitCond, so a communication timeout comes to the ERROR handler below instead
        ! of stopping the program with a fatal error.
        IF EGM_TRACK THEN
            EGMRunJoint egm_id,EGM_STOP_HOLD\J1\J2\J3\J4\J5\J6\J7
                \CondTime:=egm_cond_time_s
                \RampInTime:=egm_ramp_in_s
                \PosCorrGain:=egm_pos_corr_gain;
        ELSE
            EGMRunJoint egm_id,EGM_STOP_HOLD\J1\J2\J3\J4\J5\J6
                \CondTime:=egm_cond_time_s
                \RampInTime:=egm_ramp_in_s
                \PosCorrGain:=egm_pos_corr_gain;
        ENDIF
        egm_status:=2;
        CleanUp;
    ERROR
        IF ERRNO=ERR_UDPUC_COMM THEN
            ! 41822 "No data from the UdpUc device": the daemon stopped streaming or the network
            ! dropped it. Hold position, release EGM and end the program normally.
            egm_status:=-41822;
            CleanUp;
            RETURN;
        ENDIF
        ! Any other EGM error (reference beyond a joint limit, speed or position deviation, mode
        ! mismatch): report it and stop with the error, so it shows on the pendant and in the log.
        egm_status:=-1;
        CleanUp;
        RAISE;
    ENDPROC

    PROC CleanUp()
        IDelete end_var_int;
        IDelete end_sig_int;
        EGMReset egm_id;
        SetDO DO_EGM_END,0;
    ENDPROC

    TRAP EndEgmTrap
        ! Runs on any change of egm_end and on DO_EGM_END going high; only an end request stops EGM.
        IF egm_end OR DOutput(DO_EGM_END)=1 THEN
            EGMStop egm_id,EGM_STOP_HOLD;
        ENDIF
    ENDTRAP
ENDMODULE

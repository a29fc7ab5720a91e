package application;

// remaster: the LBR iiwa side of the FRI commander (drivers/kuka_fri/commander.py).
// Sunrise.OS 1.11-1.16 and 2.x with the Sunrise.FRI option; RoboticsAPI. NOT compiled against
// KUKA's jars by us (they are not public): build it in Sunrise Workbench and try it in T1 first.
//
// What it does: hold the robot where it is under a joint-position FRI overlay, so that the cell
// PC commands absolute joint positions; when the FRI connection drops (MONITORING_WAIT) the
// overlay motion ends, and the application waits for the client to answer again and restarts
// it, until the operator stops the application. Our fake Sunrise behaves the same
// (FakeSunrise(application=True)).
//
// FRI parameters, in one place (tests/drivers/kuka_fri/test_fri_controller_files.py checks them
// against the commander's defaults):
//   CLIENT_PORT      30200   fri://0.0.0.0:30200 on the cell PC
//   SEND_PERIOD_MS   5       the commander follows whatever period the controller sends
//   RECEIVE_MULT     1       answer every message
//   CLIENT_IP        the cell PC's address (edit)

import static com.kuka.roboticsAPI.motionModel.BasicMotions.positionHold;

import java.util.concurrent.TimeUnit;

import com.kuka.connectivity.fastRobotInterface.ClientCommandMode;
import com.kuka.connectivity.fastRobotInterface.FRIConfiguration;
import com.kuka.connectivity.fastRobotInterface.FRIJointOverlay;
import com.kuka.connectivity.fastRobotInterface.FRISession;
import com.kuka.connectivity.fastRobotInterface.FRISessionState;
import com.kuka.roboticsAPI.applicationModel.RoboticsAPIApplication;
import com.kuka.roboticsAPI.deviceModel.LBR;
import com.kuka.roboticsAPI.motionModel.controlModeModel.PositionControlMode;

public class RemasterFriApp extends RoboticsAPIApplication {
    static final String CLIENT_IP = "192.168.1.10";
    static final int CLIENT_PORT = 30200;
    static final int SEND_PERIOD_MS = 5;
    static final int RECEIVE_MULT = 1;
    static final int CONNECT_TIMEOUT_S = 60;

    private LBR lbr;

    @Override
    public void initialize() {
        lbr = getContext().getDeviceFromType(LBR.class);
    }

    @Override
    public void run() {
        FRIConfiguration config = FRIConfiguration.createRemoteConfiguration(lbr, CLIENT_IP);
        config.setPortOnRemote(CLIENT_PORT);
        config.setSendPeriodMilliSec(SEND_PERIOD_MS);
        config.setReceiveMultiplier(RECEIVE_MULT);
        FRISession session = new FRISession(config);
        try {
            while (true) {
                getLogger().info("remaster: waiting for the FRI client on " + CLIENT_IP + ":" + CLIENT_PORT);
                session.await(CONNECT_TIMEOUT_S, TimeUnit.SECONDS);  // MONITORING_READY
                FRIJointOverlay overlay = new FRIJointOverlay(session, ClientCommandMode.POSITION);
                getLogger().info("remaster: joint-position overlay on; the cell PC commands the robot");
                try {
                    // holds until the overlay ends: the client stops answering, or the operator
                    lbr.move(positionHold(new PositionControlMode(), -1, TimeUnit.SECONDS).addMotionOverlay(overlay));
                } catch (RuntimeException e) {
                    getLogger().warn("remaster: overlay motion ended: " + e.getMessage());
                }
                if (session.getFRIChannelInformation().getFRISessionState() == FRISessionState.IDLE) {
                    break;
                }
            }
        } catch (java.util.concurrent.TimeoutException e) {
            getLogger().error("remaster: no FRI client answered within " + CONNECT_TIMEOUT_S + " s");
        } finally {
            session.close();
        }
    }
}

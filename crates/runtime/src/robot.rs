//! The robot's joint table: which joints the model sees, in which order, and
//! how each servo's raw position register becomes an angle.
//!
//! Data enters as raw Present Position register values (`u16`, as read off a
//! Dynamixel bus) and leaves as angles in pypot's convention, the convention
//! the model is trained in (simulation and real robot alike):
//!
//! ```text
//! motor_deg = range_deg * raw / raw_max - range_deg / 2     (MX: 360, 4095; AX-12: 300, 1023)
//! angle_deg = (direct ? motor_deg : -motor_deg) - offset_deg
//! angle_rad = angle_deg * pi / 180
//! ```
//!
//! The inverse (`angle -> raw`) is pypot's `degree_to_dxl`: rounded to the
//! nearest unit and clamped to the register's range. pypot additionally rounds
//! its degrees to 0.01; this table does not (0.01 deg = 1.7e-4 rad).
//!
//! The model order is the table order: the 25 Poppy Humanoid motors by id,
//! ascending (`docs/contracts.md`, `/joint_states` `name`).

use std::f64::consts::PI;

/// The Dynamixel servo models on a Poppy Humanoid.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ServoModel {
    /// MX-28: 12 bit position, 360 degrees.
    Mx28,
    /// MX-64: 12 bit position, 360 degrees.
    Mx64,
    /// AX-12: 10 bit position, 300 degrees.
    Ax12,
}

impl ServoModel {
    /// The model's name as pypot and ROBOTIS write it (`"MX-28"`).
    pub fn name(self) -> &'static str {
        match self {
            ServoModel::Mx28 => "MX-28",
            ServoModel::Mx64 => "MX-64",
            ServoModel::Ax12 => "AX-12",
        }
    }

    /// The value of the Model Number register (address 0, 2 bytes).
    pub fn model_number(self) -> u16 {
        match self {
            ServoModel::Mx28 => 29,
            ServoModel::Mx64 => 310,
            ServoModel::Ax12 => 12,
        }
    }

    /// The largest Present Position value (4095 on MX, 1023 on AX).
    pub fn raw_max(self) -> u16 {
        match self {
            ServoModel::Mx28 | ServoModel::Mx64 => 4095,
            ServoModel::Ax12 => 1023,
        }
    }

    /// The angle covered by `0..=raw_max`, in degrees (360 on MX, 300 on AX).
    pub fn range_deg(self) -> f64 {
        match self {
            ServoModel::Mx28 | ServoModel::Mx64 => 360.0,
            ServoModel::Ax12 => 300.0,
        }
    }

    /// The motor's own angle (before orientation and offset), in degrees,
    /// centred on 0: pypot's `dxl_to_degree`.
    pub fn raw_to_motor_deg(self, raw: u16) -> f64 {
        let range = self.range_deg();
        range * f64::from(raw) / f64::from(self.raw_max()) - range / 2.0
    }

    /// The register value for a motor angle in degrees: pypot's
    /// `degree_to_dxl`, rounded and clamped to `0..=raw_max`.
    pub fn motor_deg_to_raw(self, motor_deg: f64) -> u16 {
        let range = self.range_deg();
        let raw = (f64::from(self.raw_max()) * (range / 2.0 + motor_deg) / range).round();
        if raw.is_nan() {
            return self.raw_max() / 2 + 1;
        }
        raw.clamp(0.0, f64::from(self.raw_max())) as u16
    }
}

/// Which way a joint's angle runs relative to its motor's.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Orientation {
    /// Joint angle = motor angle (before the offset).
    Direct,
    /// Joint angle = minus the motor angle (before the offset).
    Indirect,
}

/// One joint of the robot: one Dynamixel servo.
#[derive(Debug, Clone, PartialEq)]
pub struct Joint {
    /// Joint name, as in pypot, the URDF and `/joint_states`.
    pub name: String,
    /// Dynamixel id on its bus.
    pub id: u8,
    /// Servo model, which fixes the raw unit.
    pub model: ServoModel,
    /// Lower angle limit in pypot's convention, degrees.
    pub lower_limit_deg: f64,
    /// Upper angle limit in pypot's convention, degrees.
    pub upper_limit_deg: f64,
    /// pypot offset, degrees (subtracted after orientation).
    pub offset_deg: f64,
    /// pypot orientation.
    pub orientation: Orientation,
    /// Name of the serial bus the servo is on (`"lower"`, `"upper"`).
    pub bus: String,
}

impl Joint {
    /// Joint angle in degrees (pypot convention) for a raw Present Position.
    pub fn raw_to_deg(&self, raw: u16) -> f64 {
        let motor_deg = self.model.raw_to_motor_deg(raw);
        let oriented = match self.orientation {
            Orientation::Direct => motor_deg,
            Orientation::Indirect => -motor_deg,
        };
        oriented - self.offset_deg
    }

    /// Joint angle in radians (pypot convention) for a raw Present Position.
    pub fn raw_to_rad(&self, raw: u16) -> f64 {
        self.raw_to_deg(raw) * PI / 180.0
    }

    /// Raw register value for a joint angle in degrees (rounded, clamped).
    pub fn deg_to_raw(&self, angle_deg: f64) -> u16 {
        let oriented = angle_deg + self.offset_deg;
        let motor_deg = match self.orientation {
            Orientation::Direct => oriented,
            Orientation::Indirect => -oriented,
        };
        self.model.motor_deg_to_raw(motor_deg)
    }

    /// Raw register value for a joint angle in radians (rounded, clamped).
    pub fn rad_to_raw(&self, angle_rad: f64) -> u16 {
        self.deg_to_raw(angle_rad * 180.0 / PI)
    }

    /// The joint angles its limits allow, degrees, lowest first: the
    /// table's limits are pypot's `angle_limit`, of the opposite sign for an
    /// indirect motor (docs/robot.md).
    pub fn angle_range_deg(&self) -> (f64, f64) {
        match self.orientation {
            Orientation::Direct => (self.lower_limit_deg, self.upper_limit_deg),
            Orientation::Indirect => (-self.upper_limit_deg, -self.lower_limit_deg),
        }
    }
}

/// One row of the Poppy table: id, name, model, lower and upper limit (deg),
/// offset (deg), orientation, bus.
type PoppyRow = (
    u8,
    &'static str,
    ServoModel,
    f64,
    f64,
    f64,
    Orientation,
    &'static str,
);

/// The joints of a robot in model order.
#[derive(Debug, Clone, PartialEq)]
pub struct JointTable {
    joints: Vec<Joint>,
}

impl JointTable {
    /// The Poppy Humanoid: 25 servos, ids ascending, as in pypot's
    /// `poppy_humanoid.json` and `docs/robot.md`.
    pub fn poppy_humanoid() -> JointTable {
        use Orientation::{Direct as D, Indirect as I};
        use ServoModel::{Ax12, Mx28, Mx64};
        #[rustfmt::skip]
        let rows: [PoppyRow; 25] = [
            (11, "l_hip_x",      Mx28,  -30.0,  28.5,   0.0, D, "lower"),
            (12, "l_hip_z",      Mx28,  -25.0,  90.0,   0.0, I, "lower"),
            (13, "l_hip_y",      Mx64, -104.0,  84.0,   2.0, D, "lower"),
            (14, "l_knee_y",     Mx28,   -3.5, 134.0,   0.0, D, "lower"),
            (15, "l_ankle_y",    Mx28,  -45.0,  45.0,   0.0, D, "lower"),
            (21, "r_hip_x",      Mx28,  -28.5,  30.0,   0.0, D, "lower"),
            (22, "r_hip_z",      Mx28,  -90.0,  25.0,   0.0, I, "lower"),
            (23, "r_hip_y",      Mx64,  -85.0, 105.0,   0.0, I, "lower"),
            (24, "r_knee_y",     Mx28, -134.0,   3.5,   0.0, I, "lower"),
            (25, "r_ankle_y",    Mx28,  -45.0,  45.0,   0.0, I, "lower"),
            (31, "abs_y",        Mx64,  -50.0,  12.0,   0.0, I, "upper"),
            (32, "abs_x",        Mx64,  -45.0,  45.0,   0.0, I, "upper"),
            (33, "abs_z",        Mx28,  -90.0,  90.0,   0.0, D, "upper"),
            (34, "bust_y",       Mx28,  -67.0,  27.0,   0.0, I, "upper"),
            (35, "bust_x",       Mx28,  -40.0,  40.0,   0.0, I, "upper"),
            (36, "head_z",       Ax12,  -90.0,  90.0,   0.0, D, "upper"),
            (37, "head_y",       Ax12,  -45.0,   6.0,  20.0, I, "upper"),
            (41, "l_shoulder_y", Mx28, -120.0, 155.0,  90.0, D, "upper"),
            (42, "l_shoulder_x", Mx28, -105.0, 110.0, -90.0, I, "upper"),
            (43, "l_arm_z",      Mx28, -105.0, 105.0,   0.0, I, "upper"),
            (44, "l_elbow_y",    Mx28, -148.0,   1.0,   0.0, D, "upper"),
            (51, "r_shoulder_y", Mx28, -155.0, 120.0,  90.0, I, "upper"),
            (52, "r_shoulder_x", Mx28, -110.0, 105.0,  90.0, I, "upper"),
            (53, "r_arm_z",      Mx28, -105.0, 105.0,   0.0, I, "upper"),
            (54, "r_elbow_y",    Mx28,   -1.0, 148.0,   0.0, I, "upper"),
        ];
        let joints = rows
            .iter()
            .map(
                |&(id, name, model, lower, upper, offset, orientation, bus)| Joint {
                    name: name.to_string(),
                    id,
                    model,
                    lower_limit_deg: lower,
                    upper_limit_deg: upper,
                    offset_deg: offset,
                    orientation,
                    bus: bus.to_string(),
                },
            )
            .collect();
        JointTable { joints }
    }

    /// For each of `names`, the angles its limits allow widened by
    /// `margin_deg` on each side, radians ([`Joint::angle_range_deg`]);
    /// unbounded for a joint the table lacks.
    pub fn ranges_rad(&self, names: &[String], margin_deg: f64) -> Vec<(f64, f64)> {
        names
            .iter()
            .map(|name| {
                self.index_of(name).and_then(|i| self.get(i)).map_or(
                    (f64::NEG_INFINITY, f64::INFINITY),
                    |j| {
                        let (lo, hi) = j.angle_range_deg();
                        (
                            (lo - margin_deg).to_radians(),
                            (hi + margin_deg).to_radians(),
                        )
                    },
                )
            })
            .collect()
    }

    /// Joint names in model order.
    pub fn names(&self) -> Vec<String> {
        self.joints.iter().map(|j| j.name.clone()).collect()
    }

    /// Number of joints.
    pub fn len(&self) -> usize {
        self.joints.len()
    }

    /// Whether the table has no joints.
    pub fn is_empty(&self) -> bool {
        self.joints.is_empty()
    }

    /// Model-order index of the joint called `name`.
    pub fn index_of(&self, name: &str) -> Option<usize> {
        self.joints.iter().position(|j| j.name == name)
    }

    /// Model-order index of the joint whose servo has Dynamixel id `id`.
    pub fn index_of_id(&self, id: u8) -> Option<usize> {
        self.joints.iter().position(|j| j.id == id)
    }

    /// All joints in model order.
    pub fn joints(&self) -> &[Joint] {
        &self.joints
    }

    /// The joint at model-order index `index`.
    pub fn get(&self, index: usize) -> Option<&Joint> {
        self.joints.get(index)
    }

    /// Bus names in order of first appearance (`["lower", "upper"]` on Poppy).
    pub fn bus_names(&self) -> Vec<String> {
        let mut names: Vec<String> = Vec::new();
        for joint in &self.joints {
            if !names.contains(&joint.bus) {
                names.push(joint.bus.clone());
            }
        }
        names
    }

    /// Dynamixel ids of the servos on bus `bus`, in model order.
    pub fn ids_on_bus(&self, bus: &str) -> Vec<u8> {
        self.joints
            .iter()
            .filter(|j| j.bus == bus)
            .map(|j| j.id)
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn joint(table: &JointTable, name: &str) -> Joint {
        let index = table.index_of(name).expect("joint in table");
        table.joints()[index].clone()
    }

    #[test]
    fn poppy_table_has_25_joints_by_ascending_id_on_two_buses() {
        let table = JointTable::poppy_humanoid();
        assert_eq!(table.len(), 25);
        let ids: Vec<u8> = table.joints().iter().map(|j| j.id).collect();
        let mut sorted = ids.clone();
        sorted.sort_unstable();
        assert_eq!(ids, sorted);
        assert_eq!(table.bus_names(), vec!["lower", "upper"]);
        assert_eq!(
            table.ids_on_bus("lower"),
            vec![11, 12, 13, 14, 15, 21, 22, 23, 24, 25]
        );
        assert_eq!(table.ids_on_bus("upper").len(), 15);
        assert_eq!(table.names()[0], "l_hip_x");
        assert_eq!(table.names()[24], "r_elbow_y");
        assert_eq!(table.index_of("head_y"), Some(16));
        assert_eq!(table.index_of_id(37), Some(16));
        assert_eq!(table.index_of("nose"), None);
        let ax: Vec<String> = table
            .joints()
            .iter()
            .filter(|j| j.model == ServoModel::Ax12)
            .map(|j| j.name.clone())
            .collect();
        assert_eq!(ax, vec!["head_z", "head_y"]);
    }

    #[test]
    fn mx_conversion_matches_hand_computed_values() {
        let table = JointTable::poppy_humanoid();
        // l_hip_x: MX-28, direct, offset 0. raw 2048 -> 360*2048/4095 - 180.
        let hip = joint(&table, "l_hip_x");
        assert!((hip.raw_to_deg(2048) - 0.043_956_043_956).abs() < 1e-9);
        assert!((hip.raw_to_deg(0) - -180.0).abs() < 1e-12);
        assert!((hip.raw_to_deg(4095) - 180.0).abs() < 1e-12);
        // raw 3000: 263.736263736 - 180 = 83.736263736 deg = 1.461464... rad
        assert!((hip.raw_to_deg(3000) - 83.736_263_736_264).abs() < 1e-9);
        assert!((hip.raw_to_rad(3000) - 1.461_473_505_516).abs() < 1e-9);
        // l_hip_y: MX-64, direct, offset 2: raw 1024 -> 90.021978 - 180 - 2.
        let hip_y = joint(&table, "l_hip_y");
        assert!((hip_y.raw_to_deg(1024) - -91.978_021_978_022).abs() < 1e-9);
        // r_knee_y: MX-28, indirect, offset 0: raw 1024 -> -(90.021978 - 180).
        let knee = joint(&table, "r_knee_y");
        assert!((knee.raw_to_deg(1024) - 89.978_021_978_022).abs() < 1e-9);
        // l_shoulder_x: indirect, offset -90: raw 1000 -> -(87.912088 - 180) + 90.
        let shoulder = joint(&table, "l_shoulder_x");
        assert!((shoulder.raw_to_deg(1000) - 182.087_912_087_912).abs() < 1e-9);
        // r_shoulder_y: indirect, offset 90: raw 3072 -> -(270.065934 - 180) - 90.
        let r_shoulder = joint(&table, "r_shoulder_y");
        assert!((r_shoulder.raw_to_deg(3072) - -180.065_934_065_934).abs() < 1e-9);
    }

    #[test]
    fn ax_conversion_matches_hand_computed_values() {
        let table = JointTable::poppy_humanoid();
        // head_z: AX-12, direct, offset 0: raw 512 -> 300*512/1023 - 150.
        let head_z = joint(&table, "head_z");
        assert!((head_z.raw_to_deg(512) - 0.146_627_565_982).abs() < 1e-9);
        assert!((head_z.raw_to_deg(1023) - 150.0).abs() < 1e-12);
        // head_y: AX-12, indirect, offset 20: raw 400 -> -(117.302053 - 150) - 20.
        let head_y = joint(&table, "head_y");
        assert!((head_y.raw_to_deg(400) - 12.697_947_214_076).abs() < 1e-9);
        assert!((head_y.raw_to_rad(400) - 0.221_620_987_130).abs() < 1e-9);
    }

    #[test]
    fn angle_to_raw_inverts_the_conversion_to_within_half_a_unit() {
        let table = JointTable::poppy_humanoid();
        for joint in table.joints() {
            let unit_deg = joint.model.range_deg() / f64::from(joint.model.raw_max());
            for raw in (0..=joint.model.raw_max()).step_by(7) {
                assert_eq!(
                    joint.deg_to_raw(joint.raw_to_deg(raw)),
                    raw,
                    "{}",
                    joint.name
                );
                assert_eq!(
                    joint.rad_to_raw(joint.raw_to_rad(raw)),
                    raw,
                    "{}",
                    joint.name
                );
            }
            let mid = (joint.lower_limit_deg + joint.upper_limit_deg) / 2.0;
            let back = joint.raw_to_deg(joint.deg_to_raw(mid));
            assert!(
                (back - mid).abs() <= unit_deg / 2.0 + 1e-9,
                "{}",
                joint.name
            );
        }
        // Clamped outside the register's range, never wrapped.
        let head_z = joint(&table, "head_z");
        assert_eq!(head_z.deg_to_raw(400.0), 1023);
        assert_eq!(head_z.deg_to_raw(-400.0), 0);
        assert_eq!(head_z.deg_to_raw(f64::NAN), 512);
    }
}

//! Our protocol 1.0 framing against rustypot's, byte for byte, through a real
//! pseudo-terminal: what rustypot writes for READ_DATA / WRITE_DATA is what
//! `protocol::packet` builds, and rustypot's own protocol-1 sync read is the
//! official 0x82 (which the USB2AX does not answer), not the 0x84 we send.

use std::io::Read;
use std::time::Duration;

use fall_guard_runtime::robot::ServoModel;
use fall_guard_runtime::sources::dynamixel::protocol::{self, instruction};
use rustypot::DynamixelProtocolHandler;
use serialport::{SerialPort, TTYPort};

/// Run `send` against the slave side of a fresh pty and return the bytes that
/// came out on the master side.
fn bytes_written_by(send: impl FnOnce(&mut TTYPort)) -> Vec<u8> {
    let (mut master, mut slave) = TTYPort::pair().expect("pty pair");
    slave
        .set_timeout(Duration::from_millis(5))
        .expect("timeout");
    send(&mut slave);
    master
        .set_timeout(Duration::from_millis(50))
        .expect("timeout");
    let mut out = Vec::new();
    let mut chunk = [0u8; 256];
    while let Ok(n) = master.read(&mut chunk) {
        if n == 0 {
            break;
        }
        out.extend_from_slice(&chunk[..n]);
    }
    out
}

#[test]
fn read_and_write_packets_match_rustypot_byte_for_byte() {
    let dph = DynamixelProtocolHandler::v1();
    // Nobody answers: rustypot times out after writing, which is all we need.
    let read = bytes_written_by(|port| {
        let _ = dph.read_with_error(port, 23, 36, 2);
    });
    assert_eq!(
        read,
        protocol::packet(23, instruction::READ_DATA, &[36, 2]).unwrap()
    );
    let write = bytes_written_by(|port| {
        let _ = dph.write(port, 41, 30, &[0x00, 0x08]);
    });
    assert_eq!(
        write,
        protocol::packet(41, instruction::WRITE_DATA, &[30, 0x00, 0x08]).unwrap()
    );
    let ping = bytes_written_by(|port| {
        let _ = dph.ping(port, 11);
    });
    assert_eq!(ping, vec![0xFF, 0xFF, 11, 2, 1, !(11u8 + 2 + 1)]);
}

#[test]
fn rustypot_protocol_1_sync_read_is_0x82_which_the_usb2ax_ignores() {
    let dph = DynamixelProtocolHandler::v1();
    let theirs = bytes_written_by(|port| {
        let _ = dph.sync_read(port, &[11, 12], 36, 2);
    });
    assert_eq!(theirs[4], instruction::SYNC_READ_OFFICIAL);
    let ours = protocol::sync_read_request(36, 2, &[11, 12]).unwrap();
    assert_eq!(ours[4], instruction::USB2AX_SYNC_READ);
    // Same framing otherwise: header, broadcast id, length, params, checksum rule.
    assert_eq!(theirs.len(), ours.len());
    assert_eq!(theirs[..4], ours[..4]);
    assert_eq!(theirs[5..9], ours[5..9]);
    assert_eq!(
        protocol::checksum(&ours[2..ours.len() - 1]),
        ours[ours.len() - 1]
    );
}

#[test]
fn present_position_of_every_poppy_model_is_the_register_read_and_model_numbers_agree() {
    // The daemon takes Present Position from rustypot's MX map; its AX map
    // (the AX-12s of the head) must agree for one sync read to cover both.
    for info in [
        rustypot::servo::dynamixel::mx::register("present_position"),
        rustypot::servo::dynamixel::ax::register("present_position"),
    ] {
        let info = info.expect("present_position in rustypot's register map");
        assert_eq!(info.addr, protocol::PRESENT_POSITION.addr);
        assert_eq!(info.size, protocol::PRESENT_POSITION.len);
        assert_eq!(
            (info.addr, info.size),
            (36, 2),
            "the control table's Present Position"
        );
    }
    for model in [ServoModel::Mx28, ServoModel::Mx64, ServoModel::Ax12] {
        let (number, _) =
            rustypot::servo::find_model(model.name()).expect("model known to rustypot");
        assert_eq!(number, model.model_number(), "{}", model.name());
    }
}

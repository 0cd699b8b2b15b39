//! Dynamixel protocol 1.0 framing, and the USB2AX SYNC_READ (0x84) that
//! rustypot does not speak.
//!
//! Bytes leave as whole packets built by [`packet`] and [`sync_read_request`]
//! (the same layout and checksum as rustypot's `PacketV1`; a test in
//! `tests/servo_protocol.rs` compares them byte for byte) and enter through
//! [`scan`], which finds the next packet in a receive buffer, resynchronising
//! on `FF FF` past any garbage and reporting how many bytes it skipped.
//!
//! ```text
//! instruction  FF FF ID LEN INST PARAMS.. CHK      LEN = params + 2
//! status       FF FF ID LEN ERR  PARAMS.. CHK      CHK = !(ID + LEN + INST/ERR + sum(PARAMS))
//! USB2AX sync read request  FF FF FE N+4 84 ADDR L ID1..IDN CHK
//! USB2AX sync read reply    FF FF FD L*N+2 00 DATA(L per id, request order; FF.. = no answer) CHK
//! ```

use thiserror::Error;

/// The id every servo listens to (and none answers).
pub const BROADCAST_ID: u8 = 0xFE;
/// The USB2AX adapter's own id: its sync read reply comes from it.
pub const USB2AX_ID: u8 = 0xFD;
/// The most ids one USB2AX sync read may name.
pub const USB2AX_MAX_SYNC_IDS: usize = 31;

/// A register's place in a servo's control table.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Register {
    /// Address in the control table.
    pub addr: u8,
    /// Size in bytes (little endian).
    pub len: u8,
}

/// Present Position, the one register the daemon reads, as rustypot's MX
/// register map places it. Every motor of a Poppy Humanoid is an MX-28,
/// MX-64 or AX-12, and rustypot's AX map puts it at the same address with
/// the same size (a test checks), so one sync read covers a bus of both.
pub static PRESENT_POSITION: std::sync::LazyLock<Register> = std::sync::LazyLock::new(|| {
    let info = rustypot::servo::dynamixel::mx::register("present_position")
        .expect("rustypot's MX register map names present_position");
    Register {
        addr: info.addr,
        len: info.size,
    }
});

/// Instruction bytes of protocol 1.0, plus the USB2AX's sync read.
pub mod instruction {
    /// PING: answered by an empty status packet.
    pub const PING: u8 = 0x01;
    /// READ_DATA: params `addr, len`.
    pub const READ_DATA: u8 = 0x02;
    /// WRITE_DATA: params `addr, data..`.
    pub const WRITE_DATA: u8 = 0x03;
    /// The official protocol 1.0 SYNC_READ (what rustypot sends): ignored by
    /// AX/MX servos and by the USB2AX.
    pub const SYNC_READ_OFFICIAL: u8 = 0x82;
    /// SYNC_WRITE: no reply.
    pub const SYNC_WRITE: u8 = 0x83;
    /// The USB2AX firmware's SYNC_READ: params `addr, len, ids..`, one reply
    /// from id 0xFD.
    pub const USB2AX_SYNC_READ: u8 = 0x84;
}

/// Protocol 1.0 checksum over `ID LEN INST/ERR PARAMS..` (the packet without
/// its `FF FF` header and without the checksum byte).
pub fn checksum(body: &[u8]) -> u8 {
    !body.iter().fold(0u8, |sum, b| sum.wrapping_add(*b))
}

/// A packet that cannot be built.
#[derive(Debug, Error, PartialEq, Eq)]
pub enum PacketError {
    /// More than 253 parameter bytes do not fit the length byte.
    #[error("{0} parameter bytes do not fit one protocol 1.0 packet (253 at most)")]
    TooLong(usize),
    /// A USB2AX sync read names 1 to 31 ids.
    #[error("a USB2AX sync read names 1 to {USB2AX_MAX_SYNC_IDS} ids, not {0}")]
    SyncIdCount(usize),
}

/// One whole packet: `FF FF id LEN byte4 params.. CHK`. `byte4` is the
/// instruction in a request and the error byte in a status packet.
pub fn packet(id: u8, byte4: u8, params: &[u8]) -> Result<Vec<u8>, PacketError> {
    if params.len() > 253 {
        return Err(PacketError::TooLong(params.len()));
    }
    let mut bytes = Vec::with_capacity(params.len() + 6);
    bytes.extend_from_slice(&[0xFF, 0xFF, id, params.len() as u8 + 2, byte4]);
    bytes.extend_from_slice(params);
    let chk = checksum(&bytes[2..]);
    bytes.push(chk);
    Ok(bytes)
}

/// The USB2AX SYNC_READ request for `len` bytes at `addr` of each of `ids`:
/// `FF FF FE N+4 84 addr len id1..idN CHK`.
pub fn sync_read_request(addr: u8, len: u8, ids: &[u8]) -> Result<Vec<u8>, PacketError> {
    if ids.is_empty() || ids.len() > USB2AX_MAX_SYNC_IDS {
        return Err(PacketError::SyncIdCount(ids.len()));
    }
    let mut params = Vec::with_capacity(ids.len() + 2);
    params.extend_from_slice(&[addr, len]);
    params.extend_from_slice(ids);
    packet(BROADCAST_ID, instruction::USB2AX_SYNC_READ, &params)
}

/// A packet found by [`scan`], checksum verified.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Packet {
    /// Sender (status) or addressee (instruction).
    pub id: u8,
    /// Instruction (request) or error byte (status).
    pub byte4: u8,
    /// Parameters.
    pub params: Vec<u8>,
}

/// What [`scan`] found at the front of a receive buffer.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Scanned {
    /// No whole packet yet. The first `garbage` bytes can never begin one
    /// and may be dropped; wait for more bytes.
    Incomplete {
        /// Bytes before the first possible packet start.
        garbage: usize,
    },
    /// A whole packet with a good checksum at `buf[garbage..end]`.
    Packet {
        /// Bytes skipped before it.
        garbage: usize,
        /// One past its last byte.
        end: usize,
        /// The packet.
        packet: Packet,
    },
    /// Something framed like a packet at `buf[garbage..end]` whose checksum
    /// is wrong: either a corrupted packet or garbage that happens to hold
    /// `FF FF`. The caller decides (see [`Scanned::BadChecksum::id`]).
    BadChecksum {
        /// Bytes skipped before it.
        garbage: usize,
        /// One past its last byte.
        end: usize,
        /// Its id byte.
        id: u8,
        /// Its length byte.
        len: u8,
    },
}

/// Find the first packet in `buf`, skipping anything before an `FF FF ID`
/// header (`ID` != `FF`) and any header whose length byte is impossible (< 2).
pub fn scan(buf: &[u8]) -> Scanned {
    let mut start = 0;
    loop {
        // Find a header: FF FF followed by a non-FF id.
        let mut found = None;
        let mut i = start;
        while i + 2 < buf.len() {
            if buf[i] == 0xFF && buf[i + 1] == 0xFF && buf[i + 2] != 0xFF {
                found = Some(i);
                break;
            }
            i += 1;
        }
        let Some(head) = found else {
            // Keep a trailing FF or FF FF: it may begin the next header.
            let keep = buf[start..]
                .iter()
                .rev()
                .take(2)
                .take_while(|&&b| b == 0xFF)
                .count();
            return Scanned::Incomplete {
                garbage: buf.len() - keep,
            };
        };
        if head + 4 > buf.len() {
            return Scanned::Incomplete { garbage: head };
        }
        let len = buf[head + 3];
        if len < 2 {
            start = head + 1;
            continue;
        }
        let end = head + 4 + usize::from(len);
        if end > buf.len() {
            return Scanned::Incomplete { garbage: head };
        }
        let id = buf[head + 2];
        if checksum(&buf[head + 2..end - 1]) != buf[end - 1] {
            return Scanned::BadChecksum {
                garbage: head,
                end,
                id,
                len,
            };
        }
        return Scanned::Packet {
            garbage: head,
            end,
            packet: Packet {
                id,
                byte4: buf[head + 4],
                params: buf[head + 5..end - 1].to_vec(),
            },
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sync_read_request_is_byte_for_byte_the_usb2ax_layout() {
        // FF FF FE N+4 84 addr L ids.. CHK, CHK = !(FE + 6 + 84 + 24 + 2 + 0B + 0C)
        let bytes = sync_read_request(36, 2, &[11, 12]).unwrap();
        let sum = 0xFEu32 + 6 + 0x84 + 36 + 2 + 11 + 12;
        assert_eq!(
            bytes,
            vec![0xFF, 0xFF, 0xFE, 6, 0x84, 36, 2, 11, 12, !(sum as u8)]
        );
        assert_eq!(
            sync_read_request(36, 2, &[]),
            Err(PacketError::SyncIdCount(0))
        );
        let ids: Vec<u8> = (1..=32).collect();
        assert_eq!(
            sync_read_request(36, 2, &ids),
            Err(PacketError::SyncIdCount(32))
        );
    }

    #[test]
    fn scan_finds_a_packet_after_garbage_holding_ff_bytes() {
        let reply = packet(USB2AX_ID, 0, &[0x00, 0x08, 0xFF, 0xFF]).unwrap();
        let mut buf = vec![0x13, 0xFF, 0x00, 0xFF, 0xFF, 0xFF];
        buf.extend_from_slice(&reply);
        match scan(&buf) {
            Scanned::Packet {
                garbage,
                end,
                packet,
            } => {
                assert_eq!(garbage, 6);
                assert_eq!(end, buf.len());
                assert_eq!(packet.id, USB2AX_ID);
                assert_eq!(packet.params, vec![0x00, 0x08, 0xFF, 0xFF]);
            }
            other => panic!("expected a packet, got {other:?}"),
        }
    }

    #[test]
    fn scan_waits_for_more_and_keeps_a_possible_header_start() {
        assert_eq!(scan(&[1, 2, 3, 0xFF]), Scanned::Incomplete { garbage: 3 });
        assert_eq!(scan(&[1, 0xFF, 0xFF]), Scanned::Incomplete { garbage: 1 });
        assert_eq!(
            scan(&[0xFF, 0xFF, 1, 4, 0]),
            Scanned::Incomplete { garbage: 0 }
        );
        // Impossible length byte: that header is garbage.
        assert_eq!(
            scan(&[0xFF, 0xFF, 1, 1, 0]),
            Scanned::Incomplete { garbage: 5 }
        );
    }

    #[test]
    fn scan_reports_a_bad_checksum_with_its_extent() {
        let mut reply = packet(11, 0, &[0x00, 0x08]).unwrap();
        *reply.last_mut().unwrap() ^= 0x55;
        assert_eq!(
            scan(&reply),
            Scanned::BadChecksum {
                garbage: 0,
                end: 8,
                id: 11,
                len: 4
            }
        );
    }

    mod properties {
        use super::super::*;
        use proptest::prelude::*;

        proptest! {
            #[test]
            fn scan_never_panics_and_stays_in_bounds(bytes in proptest::collection::vec(any::<u8>(), 0..80)) {
                match scan(&bytes) {
                    Scanned::Incomplete { garbage } => prop_assert!(garbage <= bytes.len()),
                    Scanned::Packet { garbage, end, packet } => {
                        prop_assert!(garbage < end && end <= bytes.len());
                        prop_assert_eq!(packet.params.len() + 6, end - garbage);
                    }
                    Scanned::BadChecksum { garbage, end, .. } => prop_assert!(garbage < end && end <= bytes.len()),
                }
            }

            #[test]
            fn a_packet_after_ff_free_garbage_is_found_whole_and_only_once_complete(
                garbage in proptest::collection::vec(0u8..0xFF, 0..20),
                id in 0u8..0xFF,
                error in any::<u8>(),
                params in proptest::collection::vec(any::<u8>(), 0..40),
            ) {
                let reply = packet(id, error, &params).unwrap();
                let mut bytes = garbage.clone();
                bytes.extend_from_slice(&reply);
                for cut in 0..bytes.len() {
                    match scan(&bytes[..cut]) {
                        Scanned::Incomplete { garbage: skipped } => prop_assert!(skipped <= garbage.len()),
                        other => prop_assert!(false, "{:?} from a prefix of {} bytes", other, cut),
                    }
                }
                let want = Scanned::Packet {
                    garbage: garbage.len(),
                    end: bytes.len(),
                    packet: Packet { id, byte4: error, params },
                };
                prop_assert_eq!(scan(&bytes), want);
            }
        }
    }
}

//! End to end: the real PTP driver over the in-memory USB link to the
//! simulated camera firmware, under virtual time. Checks the frame, the
//! physical time each phase takes, and how every injected fault reaches the
//! engine as an `ErrorKind`.

use std::sync::Arc;
use std::time::Duration;

use rigd::rig::drivers::ptp::{PtpCamera, PtpConfig};
use rigd::rig::drivers::usb::{memory_pair, MemoryPipe};
use rigd::rig::hal::{Camera, ErrorKind};
use rigd_core::{Cfa, Clock};
use rigd_sim::devices::{CameraTimes, SimContext};
use rigd_sim::firmware::dng::{encode as encode_dng, to_raw, DngCamera};
use rigd_sim::firmware::ptp::{PtpCameraSpec, PtpFirmware};
use rigd_sim::scene::Shot;
use rigd_sim::{FaultInjector, FaultRule};

const EXPOSURE_S: f64 = 0.1;
const READOUT_S: f64 = 0.2;
const TRANSFER_S: f64 = 0.3;

/// A camera with 320 × 240 frames: larger than one 64 KiB bulk read, so the
/// driver must join several reads into one data phase.
fn rig(faults: &[&str], bit_depth: u8) -> (PtpCamera<MemoryPipe>, Clock) {
    rig_with(faults, bit_depth, PtpConfig::default())
}

/// [`rig`] with the driver's settings given.
fn rig_with(faults: &[&str], bit_depth: u8, config: PtpConfig) -> (PtpCamera<MemoryPipe>, Clock) {
    let clock = Clock::virtual_time();
    let rules: Vec<FaultRule> = faults
        .iter()
        .map(|s| s.parse().unwrap_or_else(|e| panic!("{e}")))
        .collect();
    let ctx = SimContext::new(clock.clone(), Arc::new(FaultInjector::new(rules)));
    let spec = PtpCameraSpec {
        name: "cam".into(),
        manufacturer: "rigd".into(),
        model: "SimCam PTP-12".into(),
        version: "1.0".into(),
        serial: "SIM0001".into(),
        times: CameraTimes {
            exposure_s: EXPOSURE_S,
            readout_s: READOUT_S,
            transfer_s: TRANSFER_S,
        },
        cfa: None,
    };
    let shot = move || Shot {
        light: [0.0, 0.0, 1.0],
        view: [0.0, 0.0, 1.0],
        width: 320,
        height: 240,
        bit_depth,
        ..Shot::default()
    };
    let (host, dev) = memory_pair();
    PtpFirmware::new(spec, ctx, Box::new(shot)).spawn(dev);
    let cam = PtpCamera::new("cam", host, clock.clone(), config);
    (cam, clock)
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() < 1e-6
}

#[tokio::test(start_paused = true)]
async fn capture_end_to_end_takes_the_physical_time() {
    let (mut cam, clock) = rig(&[], 12);
    let info = cam.connect().await.unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(info.model, "SimCam PTP-12");
    assert_eq!(info.serial_number, "SIM0001");
    assert_eq!(clock.now_s(), 0.0, "identification costs no time");

    cam.set_exposure(0.25)
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    let t0 = clock.now_s();
    cam.expose().await.unwrap_or_else(|e| panic!("{e}"));
    let t1 = clock.now_s();
    assert!(close(t1 - t0, 0.25 + READOUT_S), "expose took {}", t1 - t0);
    let f = cam.transfer().await.unwrap_or_else(|e| panic!("{e}"));
    let t2 = clock.now_s();
    assert!(close(t2 - t1, TRANSFER_S), "transfer took {}", t2 - t1);
    assert_eq!((f.width, f.height, f.bit_depth), (320, 240, 12));
    assert_eq!(f.pixels.len(), 320 * 240);
    assert!(f.validate("cam").is_ok());
    // The frame is the camera's DNG, kept as delivered.
    let original = f.original.as_ref().expect("the camera's file");
    assert_eq!(original.extension, "dng");
    assert_eq!(&original.bytes[..4], b"II*\0");
    let bright_long = f.pixels.iter().map(|&p| p as u64).sum::<u64>();

    // A shorter exposure gives a darker frame, and a second capture works.
    cam.set_exposure(0.05)
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    cam.expose().await.unwrap_or_else(|e| panic!("{e}"));
    let f2 = cam.transfer().await.unwrap_or_else(|e| panic!("{e}"));
    let bright_short = f2.pixels.iter().map(|&p| p as u64).sum::<u64>();
    assert!(
        bright_short * 2 < bright_long,
        "{bright_short} vs {bright_long}"
    );

    // Transferred frames are gone: nothing is pending.
    let e = cam.transfer().await.err().map(|e| e.kind);
    assert_eq!(e, Some(ErrorKind::NotReady));
}

#[tokio::test(start_paused = true)]
async fn the_profile_s_iso_is_set_at_connect_and_a_camera_without_it_is_refused() {
    let mean = |f: &rigd::rig::hal::Frame| {
        f.pixels.iter().map(|&p| f64::from(p)).sum::<f64>() / f.pixels.len() as f64
    };
    let mut means = Vec::new();
    for iso in [None, Some(200)] {
        let config = PtpConfig {
            exposure_index: iso,
            ..PtpConfig::default()
        };
        let (mut cam, _clock) = rig_with(&[], 12, config);
        cam.connect().await.unwrap_or_else(|e| panic!("{e}"));
        cam.set_exposure(0.02)
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        cam.expose().await.unwrap_or_else(|e| panic!("{e}"));
        let f = cam.transfer().await.unwrap_or_else(|e| panic!("{e}"));
        means.push(mean(&f) - 255.0);
    }
    // ISO 200 doubles the signal above black (ISO 100 is the camera's own).
    let ratio = means[1] / means[0];
    assert!((ratio - 2.0).abs() < 0.05, "{means:?}");

    let (host, dev) = memory_pair();
    scripted_camera(dev, whole(rigd_proto::ptp::FORMAT_DNG, dng(None)));
    let config = PtpConfig {
        exposure_index: Some(100),
        ..PtpConfig::default()
    };
    let mut cam = PtpCamera::new("cam", host, Clock::virtual_time(), config);
    let e = cam.connect().await.expect_err("no ExposureIndex");
    assert_eq!(e.kind(), ErrorKind::DeviceFault);
    assert!(e.to_string().contains("no ExposureIndex property"), "{e}");
}

#[tokio::test(start_paused = true)]
async fn sixteen_bit_frames_arrive_intact() {
    let (mut cam, _clock) = rig(&[], 16);
    cam.connect().await.unwrap_or_else(|e| panic!("{e}"));
    cam.set_exposure(0.1)
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    cam.expose().await.unwrap_or_else(|e| panic!("{e}"));
    let f = cam.transfer().await.unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(f.bit_depth, 16);
    assert!(f.pixels.iter().any(|&p| p > 4095), "16-bit values expected");
}

#[tokio::test(start_paused = true)]
async fn calls_out_of_order_are_not_ready_or_out_of_limits() {
    let (mut cam, _clock) = rig(&[], 12);
    let e = cam.set_exposure(0.1).await.err().map(|e| e.kind);
    assert_eq!(e, Some(ErrorKind::NotReady), "before connect");
    cam.connect().await.unwrap_or_else(|e| panic!("{e}"));
    for bad in [0.0, -1.0, f64::NAN, f64::INFINITY, 1e9, 1e-6] {
        let e = cam.set_exposure(bad).await.err().map(|e| e.kind);
        assert_eq!(e, Some(ErrorKind::OutOfLimits), "{bad}");
    }
    let e = cam.transfer().await.err().map(|e| e.kind);
    assert_eq!(e, Some(ErrorKind::NotReady), "nothing exposed");
}

#[tokio::test(start_paused = true)]
async fn timeout_fault_hits_the_deadline_and_the_camera_recovers() {
    let (mut cam, clock) = rig(&["cam:expose:1:timeout"], 12);
    cam.connect().await.unwrap_or_else(|e| panic!("{e}"));
    let e = cam
        .expose()
        .await
        .err()
        .unwrap_or_else(|| panic!("must time out"));
    assert_eq!(e.kind, ErrorKind::Timeout);
    assert!(e.message.contains("InitiateCapture"), "{}", e.message);
    let deadline = PtpConfig::default().transaction_timeout.as_secs_f64();
    assert!(close(clock.now_s(), deadline), "{}", clock.now_s());
    // The camera answers the next transaction.
    cam.expose().await.unwrap_or_else(|e| panic!("{e}"));
    cam.transfer().await.unwrap_or_else(|e| panic!("{e}"));
}

#[tokio::test(start_paused = true)]
async fn disconnect_fault_is_disconnected() {
    let (mut cam, _clock) = rig(&["cam:expose:1:disconnect"], 12);
    cam.connect().await.unwrap_or_else(|e| panic!("{e}"));
    let e = cam.expose().await.err().map(|e| e.kind);
    assert_eq!(e, Some(ErrorKind::Disconnected));
    let e = cam.set_exposure(0.1).await.err().map(|e| e.kind);
    assert_eq!(e, Some(ErrorKind::Disconnected), "the link stays closed");
}

#[tokio::test(start_paused = true)]
async fn alarm_fault_is_a_device_fault_naming_the_response() {
    let (mut cam, _clock) = rig(&["cam:set_exposure:1:alarm=iris stuck"], 12);
    cam.connect().await.unwrap_or_else(|e| panic!("{e}"));
    let e = cam
        .set_exposure(0.1)
        .await
        .err()
        .unwrap_or_else(|| panic!("alarm"));
    assert_eq!(e.kind, ErrorKind::DeviceFault);
    assert!(e.message.contains("GeneralError (0x2002)"), "{}", e.message);
    assert_eq!(e.device, "cam");
    cam.set_exposure(0.1)
        .await
        .unwrap_or_else(|e| panic!("{e}"));
}

#[tokio::test(start_paused = true)]
async fn bad_frame_fault_is_a_bad_frame_and_the_transfer_can_be_repeated() {
    let (mut cam, clock) = rig(&["cam:transfer:1:bad-frame"], 12);
    cam.connect().await.unwrap_or_else(|e| panic!("{e}"));
    cam.expose().await.unwrap_or_else(|e| panic!("{e}"));
    let t0 = clock.now_s();
    let e = cam
        .transfer()
        .await
        .err()
        .unwrap_or_else(|| panic!("bad frame"));
    assert_eq!(e.kind, ErrorKind::BadFrame);
    assert!(e.message.contains("truncated"), "{}", e.message);
    assert!(close(clock.now_s() - t0, TRANSFER_S));
    // The object stayed on the camera: the retry reads it whole.
    let f = cam.transfer().await.unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(f.pixels.len(), 320 * 240);
}

#[tokio::test(start_paused = true)]
async fn a_dead_camera_is_noticed_within_the_deadline() {
    // Nobody serves the device end: every transaction must time out.
    let clock = Clock::virtual_time();
    let (host, _dev) = memory_pair();
    let config = PtpConfig {
        transaction_timeout: Duration::from_secs(2),
        ..PtpConfig::default()
    };
    let mut cam = PtpCamera::new("cam", host, clock.clone(), config);
    let e = cam.connect().await.err().map(|e| e.kind());
    assert_eq!(e, Some(ErrorKind::Timeout));
    assert!(close(clock.now_s(), 2.0));
}

/// What a scripted camera says of its one object, and the object.
struct Scripted {
    format: u16,
    /// ObjectCompressedSize as announced.
    announced: u32,
    payload: Vec<u8>,
}

/// A scripted camera whose objects may disagree with what it announces, or
/// with the profile: the driver must refuse those, not deliver them.
fn scripted_camera(mut dev: rigd::rig::drivers::usb::MemoryDevice, object: Scripted) {
    use rigd_proto::ptp::{
        Container, ContainerKind, DeviceInfo, EventCode, ObjectInfo, OpCode, ResponseCode,
    };
    tokio::spawn(async move {
        let send = |dev: &rigd::rig::drivers::usb::MemoryDevice, c: Container, int: bool| {
            let b = c.encode().unwrap_or_else(|e| panic!("{e}"));
            let r = if int {
                dev.write_interrupt(b)
            } else {
                dev.write_in(b)
            };
            r.unwrap_or_else(|e| panic!("{e}"));
        };
        let ok = |tid| {
            Container::with_params(ContainerKind::Response, ResponseCode::OK.0, tid, &[])
                .unwrap_or_else(|e| panic!("{e}"))
        };
        while let Ok(b) = dev.read_out().await {
            let c = Container::decode(&b).unwrap_or_else(|e| panic!("{e}"));
            let tid = c.transaction_id;
            match OpCode(c.code) {
                OpCode::GetDeviceInfo => {
                    let info = DeviceInfo {
                        operations_supported: OpCode::ALL.iter().map(|o| o.0).collect(),
                        ..DeviceInfo::default()
                    };
                    send(&dev, Container::data(c.code, tid, info.encode()), false);
                }
                OpCode::InitiateCapture => {
                    send(&dev, ok(tid), false);
                    for (ev, p) in [
                        (EventCode::ObjectAdded, vec![7]),
                        (EventCode::CaptureComplete, vec![]),
                    ] {
                        let e = Container::with_params(ContainerKind::Event, ev.0, tid, &p)
                            .unwrap_or_else(|e| panic!("{e}"));
                        send(&dev, e, true);
                    }
                    continue;
                }
                OpCode::GetObjectInfo => {
                    // Real cameras give the rendered JPEG's size for raw
                    // files: the driver must not hold the file to it.
                    let info = ObjectInfo {
                        object_format: object.format,
                        compressed_size: object.announced,
                        image_width: 6000,
                        image_height: 4000,
                        image_bit_depth: 24,
                        ..ObjectInfo::default()
                    };
                    send(&dev, Container::data(c.code, tid, info.encode()), false);
                }
                OpCode::GetObject => {
                    let payload = object.payload.clone();
                    send(&dev, Container::data(c.code, tid, payload), false);
                }
                _ => {}
            }
            send(&dev, ok(tid), false);
        }
    });
}

/// The samples of the scripted 4 × 2 frames, before the black level.
const SCRIPTED: [u16; 8] = [0, 500, 1000, 1500, 2000, 2500, 3000, 4095];

/// A 4 × 2 DNG of a 12-bit sensor behind `cfa` (None: monochrome).
fn dng(cfa: Option<Cfa>) -> Vec<u8> {
    let camera = DngCamera {
        make: "Test",
        model: "Scripted",
        cfa,
        bit_depth: 12,
    };
    let raw = to_raw(&SCRIPTED, 12);
    encode_dng(&camera, 4, 2, &raw, 0.1).unwrap_or_else(|e| panic!("{e}"))
}

/// A 4 × 4 red JPEG, as a camera set to JPEG sends it.
fn jpeg() -> Vec<u8> {
    let mut out = Vec::new();
    let pixels: Vec<u8> = (0..16).flat_map(|_| [220u8, 20, 20]).collect();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 95)
        .encode(&pixels, 4, 4, image::ExtendedColorType::Rgb8)
        .unwrap_or_else(|e| panic!("{e}"));
    out
}

async fn fetch_scripted(
    object: Scripted,
    cfa: Option<Cfa>,
) -> Result<rigd::rig::hal::Frame, rigd::rig::hal::DeviceError> {
    let (host, dev) = memory_pair();
    scripted_camera(dev, object);
    let config = PtpConfig {
        cfa,
        cfa_key: "devices.cam.intrinsics.cfa".into(),
        ..PtpConfig::default()
    };
    let mut cam = PtpCamera::new("cam", host, Clock::virtual_time(), config);
    cam.connect().await.unwrap_or_else(|e| panic!("{e}"));
    cam.expose().await.unwrap_or_else(|e| panic!("{e}"));
    cam.transfer().await
}

fn whole(format: u16, payload: Vec<u8>) -> Scripted {
    Scripted {
        format,
        announced: payload.len() as u32,
        payload,
    }
}

#[tokio::test(start_paused = true)]
async fn a_camera_file_is_kept_as_delivered_and_read_by_its_bytes() {
    use rigd_proto::ptp::{FORMAT_DNG, FORMAT_EXIF_JPEG, FORMAT_UNDEFINED};
    let file = dng(Some(Cfa::Rggb));
    // DNG, or the same file labelled Undefined as some bodies do.
    for format in [FORMAT_DNG, FORMAT_UNDEFINED] {
        let f = fetch_scripted(whole(format, file.clone()), Some(Cfa::Rggb))
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        let original = f.original.expect("the file");
        assert_eq!((original.extension, &original.bytes), ("dng", &file));
        assert_eq!((f.width, f.height, f.bit_depth), (4, 2, 12));
        assert_eq!(f.pixels, to_raw(&SCRIPTED, 12));
    }
    let monochrome = fetch_scripted(whole(FORMAT_DNG, dng(None)), None).await;
    assert!(monochrome.is_ok(), "{monochrome:?}");
    // A JPEG is RGB already: there is no filter array to hold it to.
    let file = jpeg();
    let f = fetch_scripted(whole(FORMAT_EXIF_JPEG, file.clone()), Some(Cfa::Rggb))
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    let original = f.original.expect("the file");
    assert_eq!((original.extension, &original.bytes), ("jpg", &file));
    assert_eq!((f.width, f.height, f.bit_depth), (4, 4, 8));
}

#[tokio::test(start_paused = true)]
async fn broken_or_unexpected_camera_files_are_refused_with_the_reason() {
    use rigd_proto::ptp::{FORMAT_ASSOCIATION, FORMAT_DNG};
    let file = dng(Some(Cfa::Rggb));
    let half = file[..file.len() / 2].to_vec();
    let cases = [
        // The data phase ends early but is whole as a container.
        (
            Scripted {
                format: FORMAT_DNG,
                announced: file.len() as u32,
                payload: half.clone(),
            },
            Some(Cfa::Rggb),
            ErrorKind::BadFrame,
            "bytes arrived",
        ),
        // Announced as it is, but no decoder opens it.
        (
            whole(FORMAT_DNG, half),
            Some(Cfa::Rggb),
            ErrorKind::BadFrame,
            "cannot be decoded",
        ),
        (
            whole(FORMAT_DNG, b"not a camera file".to_vec()),
            None,
            ErrorKind::BadFrame,
            "not a camera file",
        ),
        // Whole, but not the sensor the profile describes: no retake mends it.
        (
            whole(FORMAT_DNG, dng(Some(Cfa::Bggr))),
            Some(Cfa::Rggb),
            ErrorKind::DeviceFault,
            "delivers a BGGR DNG frame but the profile describes a RGGB sensor; \
             set `devices.cam.intrinsics.cfa` = \"BGGR\"",
        ),
        (
            whole(FORMAT_DNG, dng(Some(Cfa::Rggb))),
            None,
            ErrorKind::DeviceFault,
            "describes a monochrome sensor",
        ),
        (
            whole(FORMAT_DNG, dng(None)),
            Some(Cfa::Rggb),
            ErrorKind::DeviceFault,
            "remove `devices.cam.intrinsics.cfa`",
        ),
        (
            whole(FORMAT_ASSOCIATION, file.clone()),
            Some(Cfa::Rggb),
            ErrorKind::DeviceFault,
            "0x3001 is no image",
        ),
    ];
    for (i, (object, cfa, kind, says)) in cases.into_iter().enumerate() {
        let e = fetch_scripted(object, cfa).await.expect_err("refused");
        assert_eq!(e.kind, kind, "case {i}: {e}");
        assert!(e.message.contains(says), "case {i}: {e}");
    }
}

// Kalibr's files as kalibr_calibrate_imu_camera writes them (no copied data),
// shared by the Kalibr import tests and the fuzz target's seeds.
#pragma once

namespace kestrel::test {

// As kalibr_calibrate_imu_camera writes it: camera looking forward along the
// IMU's x, 4 cm ahead, 1.5 cm left, 2 cm up, a small extra rotation.
inline const char* kCamchain = R"(cam0:
  T_cam_imu:
  - [0.01745240643728351, -0.9998476951563913, 0.0, 0.015]
  - [0.0, 0.0, -1.0, 0.02]
  - [0.9998476951563913, 0.01745240643728351, 0.0, -0.04]
  - [0.0, 0.0, 0.0, 1.0]
  cam_overlaps: []
  camera_model: pinhole
  distortion_coeffs: [0.0412, -0.0311, 0.00052, -0.00031]
  distortion_model: radtan
  intrinsics: [612.31, 611.87, 321.42, 238.15]
  resolution: [640, 480]
  rostopic: /camera/color/image_raw
  timeshift_cam_imu: 0.0052131
)";

inline const char* kImuYaml = R"(#Accelerometers
accelerometer_noise_density: 1.86e-03   #Noise density (continuous-time)
accelerometer_random_walk:   4.33e-04   #Bias random walk

#Gyroscopes
gyroscope_noise_density:     1.87e-04   #Noise density (continuous-time)
gyroscope_random_walk:       2.66e-05   #Bias random walk

rostopic:                    /camera/imu      #the IMU ROS topic
update_rate:                 400.0      #Hz (for discretization of the values above)
)";

}  // namespace kestrel::test

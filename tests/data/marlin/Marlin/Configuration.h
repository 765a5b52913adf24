/* test fixture in the shape of a Marlin Configuration.h (Chiron example), written for dmdsm's tests */
#pragma once
#define CONFIGURATION_H_VERSION 02010300
#ifndef MOTHERBOARD
  #define MOTHERBOARD BOARD_TRIGORILLA_14
#endif
#define BAUDRATE 250000
//#define I_DRIVER_TYPE  A4988
#define E0_DRIVER_TYPE A4988
//#define E1_DRIVER_TYPE A4988
#ifdef I_DRIVER_TYPE
  #define AXIS4_NAME 'A' // :['A', 'B', 'C', 'U', 'V', 'W']
  #define AXIS4_ROTATES
#endif
#define EXTRUDERS 1
#define TEMP_SENSOR_0 5
#define TEMP_SENSOR_BED 1
#define PIDTEMP           // PID for the hotend
//#define PIDTEMPBED
#define PREVENT_COLD_EXTRUSION
#define PREVENT_LENGTHY_EXTRUDE
#define THERMAL_PROTECTION_HOTENDS // hotend runaway
#define THERMAL_PROTECTION_BED     // bed runaway
#define THERMAL_PROTECTION_CHAMBER // chamber runaway
#define THERMAL_PROTECTION_COOLER  // cooler runaway
#define DEFAULT_AXIS_STEPS_PER_UNIT   { 80, 100, 400, 405 }
#define DEFAULT_MAX_FEEDRATE          { 200, 200, 25, 25 }
#define DEFAULT_MAX_ACCELERATION      { 350, 350, 50, 10000 }
#define DEFAULT_ACCELERATION           350    // printing moves
//#define CLASSIC_JERK
#if DISABLED(CLASSIC_JERK)
  #define JUNCTION_DEVIATION_MM 0.013 // (mm) Distance from real junction edge
  #define JD_HANDLE_SMALL_SEGMENTS    // Use curvature estimation instead of just the junction angle
#endif
//#define S_CURVE_ACCELERATION
#define FIX_MOUNTED_PROBE
//#define I_ENABLE_ON 0
//#define INVERT_I_DIR false
//#define I_HOME_DIR -1
//#define I_MIN_POS 0
//#define I_MAX_POS 50
#define FILAMENT_RUNOUT_SENSOR
#define AUTO_BED_LEVELING_BILINEAR
//#define MANUAL_I_HOME_POS 0
#define HOMING_FEEDRATE_MM_M { (50*60), (35*60), (5*60) }
#define HOST_KEEPALIVE_FEATURE        // busy messages
#define DEFAULT_KEEPALIVE_INTERVAL 2  // seconds
#define NOZZLE_PARK_FEATURE
#define SDSUPPORT
#define SPEAKER
#define ANYCUBIC_LCD_CHIRON

/* test fixture in the shape of a Marlin Configuration_adv.h (Chiron example), written for dmdsm's tests */
#pragma once
#define CONFIGURATION_ADV_H_VERSION 02010300
#define AUTOTEMP
#define HOTEND_IDLE_TIMEOUT
#define E0_AUTO_FAN_PIN 44
#define DEFAULT_MINSEGMENTTIME        20000   // (us) Set with M205 B.
#define SLOWDOWN
#if ENABLED(SLOWDOWN)
  #define SLOWDOWN_DIVISOR 2
#endif
#define HOMING_BUMP_MM      { 5, 5, 2 }       // backoff
#define HOMING_BUMP_DIVISOR { 2, 2, 4 }       // re-bump divisor
#define Z_STEPPER_AUTO_ALIGN
#define BABYSTEPPING
#define LIN_ADVANCE
#define MAX_CMD_SIZE 96
#define BUFSIZE 4
#define TX_BUFFER_SIZE 0
#define EMERGENCY_PARSER
//#define ADVANCED_OK
#define ADVANCED_PAUSE_FEATURE
//#define M114_DETAIL         // details
//#define M114_REALTIME       // real position
#define AUTO_REPORT_TEMPERATURES
//#define AUTO_REPORT_POSITION
